#!/bin/bash
# The CUDA checklist, on a machine with an NVIDIA GPU and the project's wheels in .whl/ (taichi,
# dill; see DEV_NOTES.md): the parity suite on Taichi's CUDA backend (no CPU fallback), the
# GPU-only tests, then the matching, tracking/backend and bundle-adjustment timings (RESULTS.md
# sections "matching-cuda", "tracking-cuda", "ba-cuda"; the last one only when BAL=FILE names
# the Ladybug-49 BAL file, problem-49-7776-pre.txt, which the repository does not hold). Logs and
# the updated RESULTS.md go to $OUT.
set -u
OUT=${OUT:-/tmp/cuda_checks}
mkdir -p "$OUT"
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=${PYTHONPATH:+$PYTHONPATH:}$PWD/app:$PWD/fast:$PWD/reference:$PWD/benchmarks
export OPENBLAS_NUM_THREADS=1 PYTHONUNBUFFERED=1 ENABLE_TAICHI_HEADER_PRINT=0
nvidia-smi -L | tee "$OUT/gpu.txt"
python3 -c "import sys, numpy, taichi; print(sys.version.split()[0], numpy.__version__, taichi.__version__)"
echo "== parity suite on CUDA"
MSLAM_FAST_ARCH=cuda timeout 330 python3 -m pytest -q -m "not gpu" -p no:cacheprovider \
  tests/parity 2>&1 | tee "$OUT/parity_cuda.log" | tail -n 25
echo "== GPU-only tests"
timeout 90 python3 -m pytest -q -m gpu -p no:cacheprovider tests 2>&1 | tee "$OUT/gpu_tests.log" | tail -n 8
echo "== matching timings"
timeout 100 python3 benchmarks/bench_matching.py --arch cuda 2>&1 | tee "$OUT/bench_matching.log" | tail -n 25
echo "== tracking and backend timings"
timeout 80 python3 benchmarks/bench_tracking.py --arch cuda 2>&1 | tee "$OUT/bench_tracking.log" | tail -n 12
if [ -n "${BAL:-}" ]; then
  echo "== bundle adjustment timings"
  timeout 120 python3 benchmarks/bench_ba.py --arch cuda --data "$BAL" --no-scipy --no-pyceres \
    --repeat 3 2>&1 | tee "$OUT/bench_ba.log" | tail -n 12
fi
cp benchmarks/RESULTS.md "$OUT/RESULTS.md"

#!/bin/bash
# The CUDA checklist, on a machine with an NVIDIA GPU and the project's wheels in .whl/ (taichi,
# dill; see DEV_NOTES.md): the parity suite on Taichi's CUDA backend (no CPU fallback), the
# GPU-only tests, then the matching, tracking/backend and bundle-adjustment timings (RESULTS.md
# sections "matching-cuda", "tracking-cuda", "ba-cuda-host" and "ba-cuda": the KITTI-00-sized
# problems on this machine's CPU and on CUDA, against g2o and native Ceres on its CPU; Ladybug-49
# as well when BAL=FILE names problem-49-7776-pre.txt, which the repository does not hold). Logs
# and the updated RESULTS.md go to $OUT.
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
echo "== bundle adjustment timings (KITTI-00-sized: this machine's CPU, then CUDA; g2o needs"
echo "   the g2opy wheel in .whl/, native Ceres a g++ and libceres-dev; Ladybug-49 when BAL=FILE)"
BA_ONLY="kitti00 kitti00-se3"
BA_DATA=()
if [ -n "${BAL:-}" ]; then
  mkdir -p /tmp/ba_data/ba && cp "$BAL" /tmp/ba_data/ba/ && BA_DATA=(--data /tmp/ba_data)
  BA_ONLY="ladybug49 $BA_ONLY"
fi
# shellcheck disable=SC2086
timeout 240 python3 benchmarks/bench_ba.py --arch cpu --section ba-cuda-host --only $BA_ONLY \
  "${BA_DATA[@]}" --repeat 1 2>&1 | tee "$OUT/bench_ba_host.log" | tail -n 12
# shellcheck disable=SC2086
timeout 240 python3 benchmarks/bench_ba.py --arch cuda --only $BA_ONLY "${BA_DATA[@]}" \
  --repeat 3 2>&1 | tee "$OUT/bench_ba.log" | tail -n 12
cp benchmarks/RESULTS.md "$OUT/RESULTS.md"

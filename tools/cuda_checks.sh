#!/bin/bash
# The CUDA checklist, on a machine with an NVIDIA GPU and the project's wheels in .whl/ (taichi,
# dill; see DEV_NOTES.md): the parity suite on Taichi's CUDA backend (no CPU fallback), the
# GPU-only tests, then the matching, tracking/backend and bundle-adjustment timings (RESULTS.md
# sections "matching-cuda", "tracking-cuda", "ba-cuda-host" and "ba-cuda": the KITTI-00-sized
# problems on this machine's CPU and on CUDA, against g2o and native Ceres on its CPU; Ladybug-49
# as well when BAL=FILE names problem-49-7776-pre.txt, which the repository does not hold); then
# the device-resident entries (section "resident-cuda"), and with the 7-Scenes clip under
# $MSLAM_DATA/seq the stages per frame at 512x384 (section "profile-512-60-fastf64-cuda") and the
# whole system on CUDA and on this machine's CPU, RGB-D prefetch off and on. Logs and the updated
# RESULTS.md go to $OUT.
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
echo "== device-resident entries: matching and fusion through the API per pair, NumPy entry"
echo "   against mslam_fast.resident (section resident-cuda), and the same on this machine's CPU"
timeout 120 python3 benchmarks/bench_resident.py --arch cuda 2>&1 | tee "$OUT/bench_resident.log" | tail -n 16
timeout 120 python3 benchmarks/bench_resident.py --arch cpu --no-write 2>&1 | tee "$OUT/bench_resident_cpu.log" | tail -n 16
SEQ=${MSLAM_DATA:-shared/data}/seq/7scenes_redkitchen_f000000-000149
if [ ! -d "$SEQ" ]; then
  echo "== no 7-Scenes clip at $SEQ (set MSLAM_DATA): stage and whole-system timings skipped"
  cp benchmarks/RESULTS.md "$OUT/RESULTS.md"
  exit 0
fi
echo "== stages per frame at 512x384 (RGB-D prior, 60 frames): CUDA, then this machine's CPU"
timeout 240 python3 benchmarks/profile_system.py --long-side 512 --frames 60 --arch cuda \
  2>&1 | tee "$OUT/profile_512_cuda.log" | tail -n 30
timeout 240 python3 benchmarks/profile_system.py --long-side 512 --frames 60 --arch cpu \
  --json "$OUT/profile_512_cpu.json" 2>&1 | tail -n 3; cat "$OUT/profile_512_cpu.json"; echo
echo "== whole system at 512x384 (150 frames): CUDA against the same machine's CPU, prefetch"
echo "   off and on; trajectories must be identical across prefetch (md5)"
for dev in cuda cpu; do
  for pf in false true; do
    timeout 300 python3 -m mslam.cli run "$SEQ" --device $dev --out "$OUT/run_${dev}_$pf" --quiet \
      --set dataset.long_side=512 --set rgbd_prior.prefetch=$pf >"$OUT/run_${dev}_$pf.log" 2>&1
    python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print(sys.argv[2], \
      'frames/s %.2f' % d['frames_per_second'], d['stage_seconds'])" \
      "$OUT/run_${dev}_$pf/summary.json" "$dev prefetch=$pf"
    md5sum "$OUT/run_${dev}_$pf/trajectory.txt"
  done
done
cp benchmarks/RESULTS.md "$OUT/RESULTS.md"

#!/bin/bash
# The CUDA checklist, on a machine with an NVIDIA GPU and the project's wheels in .whl/ (taichi,
# dill, and numpy < 2.5 where the machine's own is newer; g2opy for the g2o column; see
# DEV_NOTES.md).
#
#   tools/cuda_checks.sh [PART ...]      PART: profile system resident ba parity gpu_tests
#                                        matching tracking (default: all, in that order)
#
# Parts, most wanted first:
#   profile    the stages per frame at 512x384 (RGB-D prior, 60 frames) on CUDA, then on this
#              machine's CPU (section "profile-512-60-fastf64-cuda")
#   system     the whole system at 512x384 (150 frames) on CUDA, prefetch off and on, and on this
#              machine's CPU; trajectories must agree across prefetch (md5)
#   resident   matching and fusion through the API per pair, NumPy entry against
#              mslam_fast.resident (section "resident-cuda"), and the same on this CPU
#   ba         the KITTI-00-sized problems on this machine's CPU, then on CUDA, against g2o (and
#              native Ceres where a g++ and libceres-dev exist); Ladybug-49 too when BAL=FILE
#              (sections "ba-cuda-host" and "ba-cuda")
#   parity     the parity suite on Taichi's CUDA backend, no CPU fallback (pytest-xdist when
#              present)
#   gpu_tests  the GPU-only tests
#   matching, tracking   the kernel timings (sections "matching-cuda", "tracking-cuda")
#
# The 7-Scenes clip is read from $MSLAM_DATA/seq; a clip packed by tools/device_data.py (its
# depth as depth.npy.xz) is unpacked first. BUDGET=SECONDS (default 540) bounds the whole
# script: each part's timeout is cut to what is left, and parts that no longer fit are skipped
# with a line saying so. ARCH=cpu runs the same commands without a GPU (a dry run of the
# checklist). Logs and the updated RESULTS.md go to $OUT.
set -u
OUT=${OUT:-/tmp/cuda_checks}
ARCH=${ARCH:-cuda}
DEADLINE=$((SECONDS + ${BUDGET:-540}))
mkdir -p "$OUT"
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=${PYTHONPATH:+$PYTHONPATH:}$PWD/app:$PWD/fast:$PWD/reference:$PWD/benchmarks
export OPENBLAS_NUM_THREADS=1 PYTHONUNBUFFERED=1 ENABLE_TAICHI_HEADER_PRINT=0
SEQ=${MSLAM_DATA:-shared/data}/seq/7scenes_redkitchen_f000000-000149
if [ -f "$SEQ/depth.npy.xz" ] && ! ls "$SEQ"/*.depth.png >/dev/null 2>&1; then
  python3 tools/device_data.py unpack "$SEQ" || exit 1
fi
nvidia-smi -L 2>&1 | tee "$OUT/gpu.txt"
python3 -c "import sys, numpy, taichi; print(sys.version.split()[0], numpy.__version__, taichi.__version__)"

# t LIMIT CMD...: run CMD under the smaller of LIMIT and the time left before the deadline.
t() {
  local limit=$1 left=$((DEADLINE - SECONDS - 5))
  shift
  if [ "$left" -lt 20 ]; then
    echo "-- skipped (budget spent): $*"
    return 124
  fi
  [ "$limit" -gt "$left" ] && limit=$left
  timeout "$limit" "$@"
}

part_profile() {
  [ -d "$SEQ" ] || { echo "-- no 7-Scenes clip at $SEQ (set MSLAM_DATA)"; return; }
  echo "== stages per frame at 512x384 (RGB-D prior, 60 frames): $ARCH, then this machine's CPU"
  t 150 python3 benchmarks/profile_system.py --long-side 512 --frames 60 --arch "$ARCH" \
    2>&1 | tee "$OUT/profile_512_$ARCH.log" | tail -n 30
  t 120 python3 benchmarks/profile_system.py --long-side 512 --frames 60 --arch cpu \
    --json "$OUT/profile_512_cpu.json" 2>&1 | tail -n 3
  cat "$OUT/profile_512_cpu.json" 2>/dev/null
  echo
}

part_system() {
  [ -d "$SEQ" ] || { echo "-- no 7-Scenes clip at $SEQ (set MSLAM_DATA)"; return; }
  echo "== whole system at 512x384 (150 frames): $ARCH (prefetch off, on) against this CPU"
  for run in "$ARCH false" "$ARCH true" "cpu true"; do
    set -- $run
    t 150 python3 -m mslam.cli run "$SEQ" --device "$1" --out "$OUT/run_$1_$2" --quiet \
      --set dataset.long_side=512 --set rgbd_prior.prefetch="$2" >"$OUT/run_$1_$2.log" 2>&1
    python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print(sys.argv[2], \
      'frames/s %.2f' % d['frames_per_second'], d['stage_seconds'])" \
      "$OUT/run_$1_$2/summary.json" "$1 prefetch=$2" 2>&1 | tail -n 1
    md5sum "$OUT/run_$1_$2/trajectory.txt" 2>&1
  done
}

part_resident() {
  echo "== device-resident entries: $ARCH (section resident-$ARCH), then this machine's CPU"
  t 100 python3 benchmarks/bench_resident.py --arch "$ARCH" 2>&1 | tee "$OUT/bench_resident.log" \
    | tail -n 16
  t 100 python3 benchmarks/bench_resident.py --arch cpu --no-write 2>&1 \
    | tee "$OUT/bench_resident_cpu.log" | tail -n 16
}

part_ba() {
  echo "== bundle adjustment (KITTI-00-sized): this machine's CPU, then $ARCH"
  local only="kitti00 kitti00-se3" data=() g2o=()
  python3 -c "import g2opy" 2>/dev/null || { echo "-- g2opy not importable: no g2o column"; g2o=(--no-g2o); }
  if [ -n "${BAL:-}" ]; then
    mkdir -p /tmp/ba_data/ba
    case "$BAL" in
      *.xz) xz -dc "$BAL" >/tmp/ba_data/ba/problem-49-7776-pre.txt ;;
      *) cp "$BAL" /tmp/ba_data/ba/ ;;
    esac
    data=(--data /tmp/ba_data)
    only="ladybug49 $only"
  fi
  # shellcheck disable=SC2086
  t 150 python3 benchmarks/bench_ba.py --arch cpu --section ba-cuda-host --only $only \
    "${data[@]}" "${g2o[@]}" --repeat 1 2>&1 | tee "$OUT/bench_ba_host.log" | tail -n 12
  # shellcheck disable=SC2086
  t 150 python3 benchmarks/bench_ba.py --arch "$ARCH" --only $only "${data[@]}" --no-g2o \
    --repeat 2 2>&1 | tee "$OUT/bench_ba.log" | tail -n 12
}

part_parity() {
  echo "== parity suite on $ARCH"
  local xd=()
  python3 -c "import xdist" 2>/dev/null && xd=(-n "$(($(nproc) > 12 ? 12 : $(nproc)))")
  MSLAM_FAST_ARCH=$ARCH t 240 python3 -m pytest -q -m "not gpu" -p no:cacheprovider "${xd[@]}" \
    tests/parity 2>&1 | tee "$OUT/parity_$ARCH.log" | tail -n 25
}

part_gpu_tests() {
  echo "== GPU-only tests"
  t 90 python3 -m pytest -q -m gpu -p no:cacheprovider tests 2>&1 | tee "$OUT/gpu_tests.log" \
    | tail -n 8
}

part_matching() {
  echo "== matching timings"
  t 100 python3 benchmarks/bench_matching.py --arch "$ARCH" 2>&1 | tee "$OUT/bench_matching.log" \
    | tail -n 25
}

part_tracking() {
  echo "== tracking and backend timings"
  t 80 python3 benchmarks/bench_tracking.py --arch "$ARCH" 2>&1 | tee "$OUT/bench_tracking.log" \
    | tail -n 12
}

parts=("$@")
[ ${#parts[@]} -eq 0 ] && parts=(profile system resident ba parity gpu_tests matching tracking)
for p in "${parts[@]}"; do
  start=$SECONDS
  "part_$p"
  echo "-- $p: $((SECONDS - start)) s (budget left $((DEADLINE - SECONDS)) s)"
done
cp benchmarks/RESULTS.md "$OUT/RESULTS.md"

#!/bin/bash
# The wheels a lent GPU machine needs for tools/cuda_checks.sh, stripped to fit its 64 MiB
# transfer limit together with the repository and .devdata/ (about 45 MB here):
#
#   tools/device_wheels.sh [PYTHON]     PYTHON: the pip to download with (default: python3)
#
# Downloads, for CPython 3.12 on manylinux x86-64, taichi 1.7.4, dill, numpy 2.4 (that
# machine's own NumPy is outside the supported range) and g2opy (the g2o column of bench_ba),
# then rewrites each wheel without what the checks never load: taichi's C API library, headers
# and assets (and its core library stripped of symbols), NumPy's tests and headers, g2opy's
# static libraries and headers. Writes .whl/ in the repository root (ignored: add `/.whl/` to
# .git/info/exclude); the checklist installs whatever it finds there.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${1:-python3}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d "$tmp" \
  taichi==1.7.4 dill "numpy>=2.4,<2.5" g2opy
mkdir -p .whl
# repack SRC DST DROP STRIP: copy a wheel, leaving out members whose name contains one of the
# comma-separated DROP parts and stripping the symbols of members ending in STRIP.
repack() {
  "$PY" - "$@" <<'PY'
import os, subprocess, sys, tempfile, zipfile
src, dst, drop, strip = sys.argv[1], sys.argv[2], sys.argv[3].split(","), sys.argv[4]
out = zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED, compresslevel=9)
with zipfile.ZipFile(src) as zin, out as zout:
    for info in zin.infolist():
        if any(d and d in info.filename for d in drop):
            continue
        data = zin.read(info.filename)
        if strip and info.filename.endswith(strip):
            with tempfile.NamedTemporaryFile(delete=False) as f:
                f.write(data)
            subprocess.run(["strip", "--strip-unneeded", f.name], check=True)
            data = open(f.name, "rb").read()
            os.unlink(f.name)
        zout.writestr(info, data)
PY
}
for w in "$tmp"/*.whl; do
  name=$(basename "$w")
  case "$name" in
    taichi-*) repack "$w" ".whl/$name" "_lib/c_api/,.data/data/include/,taichi/assets/,/examples/" \
      "taichi_python.cpython-312-x86_64-linux-gnu.so" ;;
    numpy-*) repack "$w" ".whl/$name" "/tests/,numpy/_core/include/" "" ;;
    g2opy-*) repack "$w" ".whl/$name" "lib64/,include/" "" ;;
    *) cp "$w" .whl/ ;;
  esac
done
du -sh .whl

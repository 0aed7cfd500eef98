#!/usr/bin/env bash
# The GPU checks, as one call of the device tool (a lent machine: one H200, the workplace's CUDA image, no network).
#
# What it runs, each in a time box, writing under $OUT (what comes back):
#   env.txt      the GPU, torch and its CUDA, the CPU count
#   pytest.log   the CUDA tests (skipped on a CPU machine): every --device cuda command against the CPU, and the
#                device-following audit (tests/test_cli_device.py, tests/test_device_following.py)
#   scale.log, scale.json
#                issue 31's figure: the whole `aimpoints` command on generated radial fields of $SIZES heliostats
#                (default 2000,10000,30000; budget 10 s at 30,000 on a GPU), first and second run, on $DEVICE
#
# Prepare once on the development machine (the folder is ignored through .git/info/exclude, never committed):
#   echo /.gpu/ >> .git/info/exclude
#   mkdir -p .gpu/data .gpu/wheels && cp -r ../shared/data/paint .gpu/data/
#   pip download pvlib pytz tzdata --no-deps -d .gpu/wheels   # the image has every other dependency
# then call the device tool's run with carry [".gpu"], command "bash benchmarks/gpu_check.sh", timeout_s 540.
# Locally (no GPU, no installs): SKIP_INSTALL=1 DEVICE=cpu SIZES=300 OUT=/tmp/g bash benchmarks/gpu_check.sh
set -uo pipefail
OUT=${OUT:-/tmp/gpu_check}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
PY=${PYTHON:-python3}
SIZES=${SIZES:-2000,10000,30000}
DEVICE=${DEVICE:-cuda}
{
    nvidia-smi -L 2>/dev/null || echo "no nvidia-smi"
    "$PY" -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.is_available())"
    echo "cpus $(nproc)"
} > "$OUT/env.txt" 2>&1
if [ -z "${SKIP_INSTALL:-}" ]; then
    "$PY" -m pip install -q --no-deps --no-index .gpu/wheels/*.whl 2>&1 | tail -2
    "$PY" -m pip install -q --no-deps --no-build-isolation -e . 2>&1 | tail -2
fi
# the tests read the real data from ../shared/data beside the checkout
if [ ! -e ../shared/data ] && [ -d .gpu/data ]; then
    mkdir -p ../shared && ln -s "$PWD/.gpu/data" ../shared/data
fi
timeout 240 "$PY" -m pytest -q -p no:cacheprovider tests/test_cli_device.py tests/test_device_following.py \
    > "$OUT/pytest.log" 2>&1
echo "pytest exit $?" >> "$OUT/pytest.log"
work=$(mktemp -d)  # the generated plants (tens of MB at 30,000 heliostats) stay on the machine
timeout 300 "$PY" benchmarks/bench_aimpoints.py --out "$work" --scale "$SIZES" --device "$DEVICE" > "$OUT/scale.log" 2>&1
echo "scale exit $?" >> "$OUT/scale.log"
cp "$work/scale.json" "$OUT/" 2>/dev/null
cat "$OUT/env.txt"
tail -5 "$OUT/pytest.log"
cat "$OUT/scale.log"

#!/usr/bin/env bash
# clppm on an NVIDIA GPU in one shot (the `device` tool's machine: no network, no OpenCL set up).
#
#   here:  bash ../shared/gpu/prepare.sh          # wheels for the GPU machine's Python into .whl/
#   there: bash bench/gpu_check.sh                 # device run, carry [".whl"], timeout_s 560 (most of it the tests' time box, 300 s)
#
# Registers NVIDIA's OpenCL driver, installs clppm from the checkout, runs its self-test, the
# README's render twice (cold: kernel builds included; warm: from pyopencl's binary cache), the
# tests in order of what a GPU is likeliest to break (each stuck test dumps its Python stack after
# T_STUCK s, and the suite is stopped by SIGINT at T_TESTS s, so pytest still prints its summary),
# then bench/devices.py.  NVIDIA's compiler takes about 35 s per relief program, so the box is
# mostly builds.  At most 8 files come back in $OUT.  TESTS=... overrides the test list.
set -u
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 CLPPM_CACHE_DIR=/tmp/clppm-cache
t0=$SECONDS
log() { echo "[$((SECONDS - t0)) s] $*" | tee -a "$OUT/check.log"; }
rm -rf /tmp/site "$CLPPM_CACHE_DIR"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
  || { log "wheel install failed"; exit 1; }
export PYTHONPATH=/tmp/site
lib=$(ls /usr/local/nvidia/lib64/libnvidia-opencl.so.1 /usr/lib/x86_64-linux-gnu/libnvidia-opencl.so.1 2>/dev/null | head -1)
[ -n "$lib" ] || lib=$(find / -xdev -name 'libnvidia-opencl.so*' 2>/dev/null | head -1)
[ -n "$lib" ] || { log "no libnvidia-opencl.so found"; exit 1; }
mkdir -p /tmp/icd && echo "$lib" > /tmp/icd/nvidia.icd
export OCL_ICD_VENDORS=/tmp/icd
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv >>"$OUT/check.log" 2>&1
python3 -m pip install -q --no-index --no-deps --no-build-isolation --target /tmp/site . >"$OUT/tests.log" 2>&1 \
  || { log "clppm install failed"; cp "$OUT/tests.log" "$OUT/install.log"; exit 1; }
# From here on the installed clppm, never the source tree in the working directory: children
# (the self-test, the tests' `python -m clppm.cli`) inherit PYTHONSAFEPATH.
export PYTHONSAFEPATH=1
log "devices: $(git rev-parse --short HEAD 2>/dev/null)"
timeout 120 python3 -m clppm.cli devices >>"$OUT/check.log" 2>&1; log "devices rc=$?"
for run in cold warm; do
  rm -rf /tmp/r && mkdir -p /tmp/r
  timeout ${T_RENDER:-120} python3 -m clppm.cli render configs/forearm.toml -o /tmp/r/forearm.exr >>"$OUT/render.log" 2>&1
  log "README render ($run) rc=$?"
  cp /tmp/r/forearm.json "$OUT/forearm-$run.json" 2>/dev/null
done
cp /tmp/r/forearm.png "$OUT/" 2>/dev/null
log "tests"
timeout -s INT -k 30 ${T_TESTS:-300} python3 -m pytest -v -p no:cacheprovider --maxfail=20 -rfEs --tb=short \
  --durations=25 -o faulthandler_timeout=${T_STUCK:-90} \
  ${TESTS:-tests/test_selftest.py tests/test_photonpass.py tests/test_gather.py tests/test_determinism.py tests/test_smooth.py tests/test_pathtracer.py tests/test_spectral.py tests/test_surface.py tests/test_render.py tests/test_stability.py tests/test_checkpoint.py tests/test_hashgrid.py tests/test_mnee.py} \
  >>"$OUT/tests.log" 2>&1
log "tests rc=$? ($(grep -E '^(=+ )?[0-9]+ (passed|failed)' "$OUT/tests.log" | tail -1))"
log "bench/devices.py"
timeout ${T_BENCH:-100} python3 bench/devices.py --repeat 2 --out /tmp/bench >>"$OUT/render.log" 2>&1
log "bench rc=$?"; cp /tmp/bench/devices.json "$OUT/" 2>/dev/null
log "done"

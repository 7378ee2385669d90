#!/usr/bin/env bash
# Oclgrind's memory checks and race detector on a tiny scene through every kernel family
# (clppm/checks/tiny.py).  `oclgrind` preloads its own OpenCL runtime, so the process sees only the
# Oclgrind platform and never loads PoCL's or Intel's LLVM (two LLVMs in one process segfault);
# its device is told a 32-item work-group limit, below the 64/128 clppm asks for, to check that
# clppm queries limits.  Fails on any report from clppm's kernels (tests/oclgrind/check_log.py).
#   bash tests/oclgrind/run.sh [PYTHON]   (default: .venv/bin/python)
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${1:-.venv/bin/python}
command -v oclgrind >/dev/null || { echo "oclgrind is not installed (apt-get install oclgrind)" >&2; exit 1; }
LOG=$(mktemp /tmp/clppm-oclgrind.XXXXXX)
# No self-test: its child would run under the simulator too (the tiny scene here is its test).
export CLPPM_NO_ICD=1 PYOPENCL_NO_CACHE=1 CLPPM_SELF_TEST=0
rc=0
oclgrind --data-races --max-wgsize 32 --num-threads "$(nproc)" --log "$LOG" \
  "$PY" tests/oclgrind/tiny_all.py "${CLPPM_OCLGRIND_PHOTONS:-400}" "${CLPPM_OCLGRIND_RES:-6x4}" || rc=$?
if [ "$rc" != 0 ]; then
  echo "the tiny scene under oclgrind exited $rc; its log:" >&2; tail -50 "$LOG" >&2; exit 1
fi
rc=0; "$PY" tests/oclgrind/check_log.py "$LOG" || rc=$?
[ "$rc" = 0 ] && rm -f "$LOG" || echo "oclgrind log kept: $LOG" >&2
exit "$rc"

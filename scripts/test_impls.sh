#!/usr/bin/env bash
# Run the kernel-vs-reference suite on other OpenCL implementations, one pytest
# process per implementation (the ICD loader reads OCL_ICD_VENDORS once).
#
#   bash scripts/test_impls.sh [IMPL...] [-- PYTEST_ARGS...]
#
# IMPL: pocl, pocl-avx2, intel, rusticl, oclgrind (default: intel rusticl).  Each is
# installed if missing (scripts/opencl_impls.sh; intel goes into .venv), then
#     .venv/bin/python -m pytest --cl-impl IMPL -m "not oclgrind" PYTEST_ARGS
# runs the suite on it (tests/conftest.py isolates it and checks the
# platform).  "-m not oclgrind" leaves out tests/test_oclgrind.py's stage runs,
# which always run on Oclgrind whatever --cl-impl says.  Oclgrind runs the
# whole suite too, but ~1000x slower than PoCL: pick tests with -k.
# Exit status: non-zero if any implementation's run failed; a summary line per
# implementation is printed at the end.
set -uo pipefail
cd "$(dirname "$0")/.."
IMPLS=()
while [ $# -gt 0 ] && [ "$1" != "--" ]; do IMPLS+=("$1"); shift; done
[ "${1:-}" = "--" ] && shift
[ ${#IMPLS[@]} -eq 0 ] && IMPLS=(intel rusticl)
[ -x .venv/bin/python ] || bash scripts/setup.sh
rc=0
SUMMARY=()
for impl in "${IMPLS[@]}"; do
    bash scripts/opencl_impls.sh "$impl" >/dev/null || { rc=1; SUMMARY+=("$impl: not installable"); continue; }
    echo "=== $impl" >&2
    log=$(mktemp)
    .venv/bin/python -m pytest -q -rfEx -p no:cacheprovider --cl-impl "$impl" -m "not oclgrind" "$@" 2>&1 | tee "$log"
    st=${PIPESTATUS[0]}
    [ "$st" -ne 0 ] && rc=1
    SUMMARY+=("$impl: $(grep -E '(passed|failed|error)' "$log" | tail -1) (exit $st)")
    rm -f "$log"
done
printf '%s\n' "${SUMMARY[@]}"
exit $rc

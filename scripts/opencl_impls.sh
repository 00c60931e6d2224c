#!/usr/bin/env bash
# Install OpenCL implementations and write one .icd file per implementation.
#
#   bash scripts/opencl_impls.sh [--no-install] [--env] [--dir DIR] [pocl|pocl-avx2|intel|oclgrind|rusticl|all]...
#
# For each implementation named (default: pocl) it installs it if missing
# (idempotent), writes DIR/<impl>.icd holding the absolute path of that
# implementation's ICD library, and prints the .icd path (one line each).
# DIR defaults to $MCCNN_CL_ICD_DIR, else $HOME/.cache/mccnn_cl/icd.
#
# Point the ICD loader at exactly one implementation with
#     OCL_ICD_VENDORS=DIR/<impl>.icd
# (PyOpenCL's bundled loader honours it; OCL_ICD_FILENAMES is ignored).
# Extra environment each one needs (tests/conftest.py sets these itself for
# `pytest --cl-impl <impl>`):
#     rusticl : RUSTICL_ENABLE=llvmpipe
#     oclgrind: OCLGRIND_DATA_RACES=1 OCLGRIND_CHECK_API=1 OCLGRIND_LOG=<file> PYOPENCL_NO_CACHE=1
#
# --no-install: only look for the library; exit 3 with an install hint when an
# implementation is missing (used by the tests, which never install).
# --env: print KEY=VALUE lines instead of the path: OCL_ICD_VENDORS and the
# implementation's own variables (one implementation only; OCLGRIND_LOG is
# left to the caller), e.g.
#     env $(bash scripts/opencl_impls.sh --env rusticl) .venv/bin/python -m pytest ...
#
#   pocl     Debian's PoCL          apt-get install pocl-opencl-icd
#   pocl-avx2  the same PoCL building AVX2 code (POCL_KERNELLIB_NAME=avx2): a Zen 3's code on any AVX2 CPU
#   intel    Intel CPU runtime      pip install intel-opencl-rt intel-cmplr-lib-rt  (into .venv)
#   oclgrind Oclgrind simulator     apt-get install oclgrind
#   rusticl  Mesa Rusticl/llvmpipe  apt-get install mesa-opencl-icd
set -euo pipefail
REPO="$(cd "$(dirname "$0")/.." && pwd)"
VENV="${VENV:-$REPO/.venv}"
DIR="${MCCNN_CL_ICD_DIR:-$HOME/.cache/mccnn_cl/icd}"
INSTALL=1
PRINT_ENV=0
IMPLS=()
while [ $# -gt 0 ]; do
    case "$1" in
        --no-install) INSTALL=0 ;;
        --env) PRINT_ENV=1 ;;
        --dir) DIR="$2"; shift ;;
        --dir=*) DIR="${1#--dir=}" ;;
        pocl|pocl-avx2|intel|oclgrind|rusticl) IMPLS+=("$1") ;;
        all) IMPLS+=(pocl pocl-avx2 intel oclgrind rusticl) ;;
        -h|--help) sed -n '2,35p' "$0"; exit 0 ;;
        *) echo "opencl_impls.sh: unknown argument '$1' (pocl|pocl-avx2|intel|oclgrind|rusticl|all|--no-install|--env|--dir DIR)" >&2; exit 2 ;;
    esac
    shift
done
[ ${#IMPLS[@]} -eq 0 ] && IMPLS=(pocl)
if [ "$PRINT_ENV" -eq 1 ] && [ ${#IMPLS[@]} -ne 1 ]; then
    echo "opencl_impls.sh: --env takes exactly one implementation" >&2; exit 2
fi
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
APT_UPDATED=0

apt_install() {  # apt_install PACKAGE...
    if [ "$APT_UPDATED" -eq 0 ]; then $SUDO apt-get update -qq; APT_UPDATED=1; fi
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "$@" >/dev/null
}

find_system_lib() {  # find_system_lib SONAME -> absolute path or nothing
    local p
    p=$(/sbin/ldconfig -p 2>/dev/null | awk -v n="$1" '$1 == n && /x86-64|x86_64|64bit/ {print $NF; exit}')
    if [ -z "$p" ]; then
        for d in /usr/lib/x86_64-linux-gnu /usr/lib64 /usr/lib /usr/local/lib; do
            [ -e "$d/$1" ] && { p="$d/$1"; break; }
        done
    fi
    [ -n "$p" ] && readlink -f "$p"
    return 0
}

lib_path() {  # lib_path IMPL -> absolute path of the ICD library, or nothing
    case "$1" in
        pocl|pocl-avx2) find_system_lib libpocl.so.2 ;;
        rusticl) find_system_lib libRusticlOpenCL.so.1 ;;
        oclgrind) [ -e /usr/lib/oclgrind/liboclgrind-rt-icd.so ] && echo /usr/lib/oclgrind/liboclgrind-rt-icd.so; return 0 ;;
        intel)
            # the wheel installs its libraries into the venv's prefix/lib; its own
            # .icd holds a build-time placeholder path, so it is not used
            [ -x "$VENV/bin/python" ] || return 0
            local prefix
            prefix=$("$VENV/bin/python" -c 'import sys; print(sys.prefix)')
            [ -e "$prefix/lib/libintelocl.so" ] && readlink -f "$prefix/lib/libintelocl.so"
            return 0 ;;
    esac
}

install_impl() {
    case "$1" in
        pocl|pocl-avx2) apt_install pocl-opencl-icd ;;
        oclgrind) apt_install oclgrind ;;
        rusticl) apt_install mesa-opencl-icd ;;
        intel)
            [ -x "$VENV/bin/python" ] || { echo "opencl_impls.sh: no venv at $VENV (run scripts/test.sh first, or set VENV)" >&2; exit 3; }
            "$VENV/bin/python" -m pip install -q intel-opencl-rt intel-cmplr-lib-rt 2>&1 | grep -v "^WARNING: Location" >&2 || true ;;
    esac
}

impl_env() {  # the implementation's own variables besides OCL_ICD_VENDORS
    case "$1" in
        rusticl) echo "RUSTICL_ENABLE=llvmpipe" ;;
        # Debian's PoCL building AVX2 code on any x86-64 CPU that has AVX2 (the
        # kernel library and LLVM CPU of a Zen 3; device pthread-haswell-...)
        pocl-avx2) echo "POCL_KERNELLIB_NAME=avx2" ;;
        oclgrind) printf '%s\n' OCLGRIND_DATA_RACES=1 OCLGRIND_CHECK_API=1 PYOPENCL_NO_CACHE=1 ;;
    esac
}

hint() {
    case "$1" in
        pocl|pocl-avx2) echo "apt-get install pocl-opencl-icd" ;;
        oclgrind) echo "apt-get install oclgrind" ;;
        rusticl) echo "apt-get install mesa-opencl-icd" ;;
        intel) echo "$VENV/bin/pip install intel-opencl-rt intel-cmplr-lib-rt" ;;
    esac
}

mkdir -p "$DIR"
for impl in "${IMPLS[@]}"; do
    lib=$(lib_path "$impl")
    if [ -z "$lib" ] && [ "$INSTALL" -eq 1 ]; then
        echo "opencl_impls.sh: installing $impl ..." >&2
        install_impl "$impl"
        lib=$(lib_path "$impl")
    fi
    if [ -z "$lib" ]; then
        echo "opencl_impls.sh: OpenCL implementation '$impl' is not installed; install it with" \
             "'bash scripts/opencl_impls.sh $impl' ($(hint "$impl"))" >&2
        exit 3
    fi
    icd="$DIR/$impl.icd"
    # rewrite only when it changes, so concurrent readers never see a partial file
    if [ ! -e "$icd" ] || [ "$(cat "$icd")" != "$lib" ]; then
        printf '%s\n' "$lib" > "$icd.tmp.$$" && mv -f "$icd.tmp.$$" "$icd"
    fi
    if [ "$PRINT_ENV" -eq 1 ]; then
        echo "OCL_ICD_VENDORS=$icd"
        impl_env "$impl"
    else
        echo "$icd"
    fi
done

# Sourced by gpu_check.sh and gpu_lease.sh: `nvidia_icd DIR` registers the NVIDIA OpenCL
# driver where a CUDA-only image ships its library (libnvidia-opencl.so.1) but no ICD file.
# When OCL_ICD_VENDORS is unset, nvidia-smi runs and /etc/OpenCL/vendors names no NVIDIA
# library, it writes DIR/nvidia.icd beside copies of the registered ICDs, exports
# OCL_ICD_VENDORS=DIR and NVIDIA_ICD_LIB=the library, and returns 0; otherwise 1. The library
# is looked up with ldconfig, then in NVIDIA_ICD_SEARCH (folders; default: the usual ones).
nvidia_icd() {
    local dir=$1 lib d
    [ -z "${OCL_ICD_VENDORS:-}" ] || return 1
    command -v nvidia-smi >/dev/null || return 1
    ! grep -qsi nvidia /etc/OpenCL/vendors/*.icd || return 1
    lib=$( (ldconfig -p 2>/dev/null | awk '/libnvidia-opencl\.so\.1/ {print $NF; exit}') || true)
    for d in ${NVIDIA_ICD_SEARCH:-/usr/local/nvidia/lib64 /usr/lib/x86_64-linux-gnu /usr/lib64 /usr/lib/aarch64-linux-gnu}; do
        [ -z "$lib" ] && [ -e "$d/libnvidia-opencl.so.1" ] && lib="$d/libnvidia-opencl.so.1"
    done
    [ -n "$lib" ] || return 1
    mkdir -p "$dir" || return 1
    cp /etc/OpenCL/vendors/*.icd "$dir"/ 2>/dev/null || true
    echo "$lib" > "$dir/nvidia.icd" || return 1
    export OCL_ICD_VENDORS=$dir NVIDIA_ICD_LIB=$lib
}

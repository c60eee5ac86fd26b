#!/usr/bin/env bash
# Compile-only check of the CUDA backend (no GPU, no linking): nvcc compiles ops/csrc/cuda/*_cuda.cu and
# the host compiler compiles ops/csrc/cuda/bindings.cpp to object files against this torch's headers and the
# CUDA toolkit's. Works with a CPU-only torch wheel (its include/ tree carries the ATen/c10 CUDA headers the
# kernels file uses). ptxas reports each kernel's registers, stack and spills (-Xptxas -v); the check fails when a
# kernel's stack exceeds its budget or a kernel that must not spill does (ops/kernel_resources.py: sample_kernel and
# merge_prepare_kernel <= 1 KiB, no spills). nvcc gets the extension's own flags (ops/build.py CUDA_CFLAGS:
# --fmad=false). What it does NOT check: linking against libtorch_cuda/libcudart, and running anything.
# Usage: bash .ci/cuda_compile_check.sh   (NVCC, CXX, CUDA_ARCH and PYTHON override the defaults)
set -euo pipefail
cd "$(dirname "$0")/.."
NVCC=${NVCC:-nvcc}
PYTHON=${PYTHON:-python}
CXX=${CXX:-g++}
ARCH=${CUDA_ARCH:-90}   # Hopper (H100/H200); any arch nvcc supports works for a compile check
command -v "$NVCC" >/dev/null 2>&1 || { echo "cuda_compile_check: nvcc not found" >&2; exit 1; }

CUDA_HOME=${CUDA_HOME:-$(cd "$(dirname "$(readlink -f "$(command -v "$NVCC")")")/.." && pwd)}
if [ ! -f "$CUDA_HOME/include/cuda_runtime.h" ]; then
  for d in /usr/local/cuda /usr/local/cuda-*; do [ -f "$d/include/cuda_runtime.h" ] && CUDA_HOME=$d && break; done
fi
[ -f "$CUDA_HOME/include/cuda_runtime.h" ] || { echo "cuda_compile_check: CUDA headers not found" >&2; exit 1; }

# torch's (and Python's) headers as system includes, as torch.utils.cpp_extension passes them.
TORCH_INC=()
while IFS= read -r dir; do TORCH_INC+=(-isystem "$dir"); done < <("$PYTHON" -c "
import sysconfig
from torch.utils.cpp_extension import include_paths
print('\\n'.join(include_paths() + [sysconfig.get_paths()['include'], '$CUDA_HOME/include']))")
STD=$("$PYTHON" -c "from nsplat.ops.build import cxx_standard; print(cxx_standard())")  # c++17, or c++20 for torch >= 2.14
CXX11_ABI=$("$PYTHON" -c "import torch; print(int(torch._C._GLIBCXX_USE_CXX11_ABI))")
DEFS=(-DTORCH_EXTENSION_NAME=nsplat_cuda -DTORCH_API_INCLUDE_EXTENSION_H -D_GLIBCXX_USE_CXX11_ABI="$CXX11_ABI")
OUTDIR=$(mktemp -d)
trap 'rm -rf "$OUTDIR"' EXIT

# A CPU-only torch wheel ships c10/cuda's headers but not the one CMake generates for them; recreate it
# (its whole content in CUDA builds of torch is the shared-library define below) so the check can run.
TORCH_ROOT_INC=$("$PYTHON" -c "from torch.utils.cpp_extension import include_paths; print(include_paths()[0])")
if [ ! -f "$TORCH_ROOT_INC/c10/cuda/impl/cuda_cmake_macros.h" ]; then
  mkdir -p "$OUTDIR/shim/c10/cuda/impl"
  printf '#pragma once\n#define C10_CUDA_BUILD_SHARED_LIBS\n' >"$OUTDIR/shim/c10/cuda/impl/cuda_cmake_macros.h"
  TORCH_INC+=(-isystem "$OUTDIR/shim")
  echo "cuda_compile_check: CPU-only torch: using a generated c10/cuda/impl/cuda_cmake_macros.h"
fi

echo "cuda_compile_check: $("$NVCC" --version | tail -1) (sm_$ARCH), CUDA_HOME=$CUDA_HOME"
# Same flags as torch.utils.cpp_extension gives nvcc, plus the extension's own (ops/build.py CUDA_CFLAGS).
read -r -a OWN_FLAGS < <("$PYTHON" -c "from nsplat.ops.build import CUDA_CFLAGS; print(' '.join(CUDA_CFLAGS))")
NVCC_PIDS=()
for kernels in splat_cuda projection_cuda; do
  "$NVCC" -c "ops/csrc/cuda/$kernels.cu" -o "$OUTDIR/$kernels.o" -std="$STD" "${OWN_FLAGS[@]}" \
    -gencode=arch=compute_$ARCH,code=sm_$ARCH --expt-relaxed-constexpr --compiler-options '-fPIC' \
    -D__CUDA_NO_HALF_OPERATORS__ -D__CUDA_NO_HALF_CONVERSIONS__ -D__CUDA_NO_BFLOAT16_CONVERSIONS__ \
    -D__CUDA_NO_HALF2_OPERATORS__ "${DEFS[@]}" -Iops/csrc "${TORCH_INC[@]}" \
    -Werror all-warnings -Xcompiler -Wall -Xptxas -v >"$OUTDIR/$kernels.ptxas" 2>&1 &
  NVCC_PIDS+=($!)
done
"$CXX" -c ops/csrc/cuda/bindings.cpp -o "$OUTDIR/bindings.o" -std="$STD" -O1 -fPIC -Wall -Werror \
  "${DEFS[@]}" -Iops/csrc "${TORCH_INC[@]}"
NVCC_RC=0
for pid in "${NVCC_PIDS[@]}"; do wait "$pid" || NVCC_RC=$?; done
# ptxas -v reports on stderr as "ptxas info"; anything else there is a diagnostic
grep -hvE "^ptxas info|bytes stack frame" "$OUTDIR"/*.ptxas || true
[ "$NVCC_RC" -eq 0 ] || { echo "cuda_compile_check: nvcc failed (rc=$NVCC_RC)" >&2; exit "$NVCC_RC"; }
echo "cuda_compile_check: per-kernel resources (sm_$ARCH; stack and spills in bytes per thread)"
cat "$OUTDIR"/*.ptxas | "$PYTHON" -m nsplat.ops.kernel_resources --format ptxas
echo "cuda_compile_check: OK ($(du -ck "$OUTDIR"/*_cuda.o | tail -1 | cut -f1) KiB kernel objects, bindings object built)"

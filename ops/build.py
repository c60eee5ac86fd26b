"""Just-in-time build of the native backends, cached; ``python -m nsplat.ops.build`` prebuilds.

The C++ sources live in ``csrc/`` beside this file: ``core/`` (header-only, host+device algorithm),
``cpu/`` (OpenMP) and ``cuda/`` (kernels). Builds go to ``$NSPLAT_BUILD_DIR`` (default
``~/.cache/nsplat/<torch version>``); PyTorch's loader rebuilds when a source changes.
"""
from __future__ import annotations

import hashlib
import importlib.util
import logging
import os
import sys
import time
from pathlib import Path
from types import ModuleType

import torch

log = logging.getLogger("nsplat.ops")
CSRC = Path(__file__).resolve().parent / "csrc"
_MODULES: dict[str, ModuleType] = {}
#: The CPU backend's sources (csrc/cpu). lanes_<isa>.cpp compile the sampler's tile search for each instruction
#: set (by `#pragma GCC target`, not by flags), lanes_dispatch.cpp picks one at run time.
CPU_SOURCES = ("bindings.cpp", "splat_cpu.cpp", "scatter_cpu.cpp", "projection_cpu.cpp", "view_colour_cpu.cpp",
               "tiled_cpu.cpp", "lanes_dispatch.cpp", "lanes_base.cpp", "lanes_avx2.cpp", "lanes_avx512.cpp")
#: The CUDA backend's sources (csrc/cuda): the Python module and the kernel files.
CUDA_SOURCES = ("bindings.cpp", "splat_cuda.cu", "projection_cuda.cu")
#: No contraction into FMA: every instruction set computes the same bits (docs/op.md §4). The C++ standard is
#: added by :func:`cxx_standard`.
CPU_CFLAGS = ("-O3", "-fopenmp", "-ffp-contract=off")
#: nvcc with the CPU's floating-point contract: no contraction into FMA (``--fmad=false``; IEEE division and square
#: root are nvcc's default), so code of +, -, *, / and sqrt alone gives the CPU's bits on a GPU (docs/op.md §4 says
#: which results that makes equal; exp and log are the device library's and are not).
CUDA_CFLAGS = ("-O3", "-lineinfo", "--fmad=false")
#: A build lock older than this is taken to be left by a killed build (a real build takes ~1-3 minutes).
STALE_LOCK_S = 900


def build_dir(kind: str) -> Path:
    """Folder holding the compiled ``kind`` ("cpu" or "cuda") extension."""
    root = Path(os.environ.get("NSPLAT_BUILD_DIR", Path.home() / ".cache" / "nsplat"))
    tag = torch.__version__.replace("+", "_")
    path = root / f"torch-{tag}" / kind
    path.mkdir(parents=True, exist_ok=True)
    return path


def cxx_standard() -> str:
    """The C++ standard the installed torch's headers need, for g++ and nvcc alike: ``c++20`` where
    ``torch/all.h`` refuses older compilers (torch 2.14 and later), else ``c++17`` (the project's own code needs
    no more)."""
    from torch.utils.cpp_extension import include_paths

    for root in include_paths():
        header = Path(root) / "torch" / "all.h"
        if header.is_file():
            return "c++20" if "202002L" in header.read_text(errors="replace") else "c++17"
    return "c++17"


def source_hash() -> str:
    """Hash of every native source and header (PyTorch's loader only hashes the listed sources)."""
    h = hashlib.sha256()
    for p in sorted(CSRC.rglob("*")):
        if p.suffix in (".h", ".cpp", ".cu"):
            h.update(p.relative_to(CSRC).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()[:16]


def _load(kind: str) -> ModuleType:
    from torch.utils.cpp_extension import load

    tag = f"-DNSPLAT_SOURCE_HASH={source_hash()}"
    std = f"-std={cxx_standard()}"
    if kind == "cpu":
        sources = [str(CSRC / "cpu" / f) for f in CPU_SOURCES]
        flags = dict(extra_cflags=[*CPU_CFLAGS, std, tag], extra_ldflags=["-fopenmp"])
    else:
        sources = [str(CSRC / "cuda" / f) for f in CUDA_SOURCES]
        flags = dict(extra_cflags=["-O3", std, tag], extra_cuda_cflags=[*CUDA_CFLAGS, std, tag])
    target = build_dir(kind)
    digest = source_hash()
    stamp = target / "source_hash"
    built = target / f"nsplat_{kind}.so"
    if built.is_file() and stamp.is_file() and stamp.read_text() == digest:
        spec = importlib.util.spec_from_file_location(f"nsplat_{kind}", built)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    lock = target / "lock"
    if lock.exists() and time.time() - lock.stat().st_mtime > STALE_LOCK_S:
        log.warning("nsplat: removing a stale build lock %s (left by an interrupted build)", lock)
        lock.unlink(missing_ok=True)
    log.warning("nsplat: compiling the %s extension into %s (first use only, about a minute)...", kind, target)
    module = load(name=f"nsplat_{kind}", sources=sources, extra_include_paths=[str(CSRC)],
                  build_directory=str(target), verbose=False, **flags)
    if Path(module.__file__).resolve() == built.resolve():
        stamp.write_text(digest)
    return module


def backend(device: torch.device) -> ModuleType:
    """The compiled module for ``device`` (built on first use)."""
    kind = "cuda" if device.type == "cuda" else "cpu"
    if kind not in _MODULES:
        if kind == "cuda" and not torch.cuda.is_available():
            raise RuntimeError("nsplat: tensors are on CUDA but CUDA is not available")
        _MODULES[kind] = _load(kind)
    return _MODULES[kind]


def main(argv: list[str] | None = None) -> int:
    """Prebuild the CPU extension, and the CUDA one when a CUDA device is present."""
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    kinds = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for kind in kinds:
        mod = backend(torch.device(kind))
        log.info("built %s backend: %s", kind, mod.__file__)
    return 0


if __name__ == "__main__":
    sys.exit(main())

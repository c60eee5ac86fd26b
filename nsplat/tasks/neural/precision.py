"""The compute precision of the neural task's networks (U-Net shader and PatchGAN): float32, or bfloat16
autocast where the CPU multiplies bfloat16 natively (the setting ``neural.precision``).

``auto`` follows the rule measured in docs/performance.md ("Network precision"): **bfloat16 when the CPU has
AMX-BF16 or AVX512-BF16** (oneDNN then runs the convolutions with its native ``avx512_core_amx`` /
``avx512_core_bf16`` kernels, faster than float32), **float32 otherwise** (bfloat16 is emulated there, slower
than float32). On CUDA ``auto`` is float32 (not measured there); ``bfloat16`` asks for CUDA autocast and needs a
GPU with bfloat16.

Only the networks run under autocast (:func:`autocast`); their outputs come back in float32, so the op (which
runs in float32 in any case, docs/op.md §7), the losses, the parameters, the optimiser state and the
checkpoints stay float32.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import AbstractSet, Literal

import torch

from nsplat.config import ConfigError

log = logging.getLogger(__name__)

Precision = Literal["auto", "float32", "bfloat16"]
#: CPU features with which oneDNN multiplies bfloat16 natively (``torch.cpu.get_capabilities`` and
#: ``/proc/cpuinfo`` spell them alike).
NATIVE_BF16 = ("amx_bf16", "avx512_bf16")


def cpu_capabilities() -> frozenset[str]:
    """The CPU's features: those ``torch.cpu.get_capabilities()`` reports true, or (torch without it) the
    ``flags`` line of ``/proc/cpuinfo`` (empty where neither exists)."""
    get = getattr(torch.cpu, "get_capabilities", None)
    if get is not None:
        return frozenset(name for name, value in get().items() if value is True)
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return frozenset()
    m = re.search(r"^flags\s*:\s*(.+)$", text, re.M)
    return frozenset(m.group(1).split()) if m else frozenset()


def auto_dtype(device: torch.device, capabilities: AbstractSet[str]) -> tuple[torch.dtype, str]:
    """``auto``'s choice on ``device`` for a CPU with ``capabilities``, and why (for the log line)."""
    if device.type != "cpu":
        return torch.float32, f"{device.type}: float32 unless asked (not measured)"
    native = [f for f in NATIVE_BF16 if f in capabilities]
    if native:
        return torch.bfloat16, f"the CPU has {' and '.join(native)}"
    return torch.float32, f"the CPU has neither {' nor '.join(NATIVE_BF16)} (bfloat16 would be emulated)"


def resolve(setting: Precision, device: torch.device, capabilities: AbstractSet[str] | None = None) -> torch.dtype:
    """The networks' compute dtype for ``neural.precision`` = ``setting`` on ``device`` (``capabilities``:
    :func:`cpu_capabilities`). ``auto`` logs its choice and the reason; ``bfloat16`` on a CUDA device
    without bfloat16 raises :class:`~nsplat.config.ConfigError`."""
    if setting == "float32":
        return torch.float32
    if setting == "bfloat16":
        if device.type == "cuda" and not torch.cuda.is_bf16_supported():
            raise ConfigError(f"neural.precision: bfloat16 is not supported by {torch.cuda.get_device_name(device)}")
        return torch.bfloat16
    if setting != "auto":
        raise ConfigError(f"neural.precision: expected one of auto, float32, bfloat16, got {setting!r}")
    dtype, why = auto_dtype(device, cpu_capabilities() if capabilities is None else capabilities)
    log.info("neural.precision: auto -> %s (%s)", str(dtype).removeprefix("torch."), why)
    return dtype


def autocast(dtype: torch.dtype, device_type: str) -> torch.autocast:
    """The region the networks run in: bfloat16 autocast on ``device_type`` when ``dtype`` is bfloat16, a
    disabled (pass-through) region for float32."""
    return torch.autocast(device_type, dtype=torch.bfloat16, enabled=dtype == torch.bfloat16)

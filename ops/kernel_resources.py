"""Registers, stack and spills of the CUDA kernels, from ``ptxas -v`` or ``cuobjdump --dump-resource-usage``.

``.ci/cuda_compile_check.sh`` pipes ptxas's report through ``python -m nsplat.ops.kernel_resources --ptxas`` and fails
when a kernel's stack frame exceeds its budget (:data:`STACK_BUDGETS`, bytes per thread) or a kernel of
:data:`NO_SPILLS` spills; ``.ci/gpu_check.sh`` prints the table of the built extension (``--cuobjdump``).
"""
from __future__ import annotations

import argparse
import dataclasses
import re
import sys

#: Stack bytes per thread a kernel may use (local memory; a pixel thread's stack times the resident threads is
#: read from L1/L2). The sampler's two searching kernels hold a lane's bins and a depth-first stack (core/tile.h,
#: core/sps.h); every other kernel gets the default.
STACK_BUDGETS = {"sample_kernel": 1024, "merge_prepare_kernel": 1024, "slot_items_kernel": 512,
                 "view_colour_backward_kernel": 512}
DEFAULT_STACK_BUDGET = 256
#: Kernels that must not spill registers.
NO_SPILLS = ("sample_kernel", "merge_prepare_kernel")


@dataclasses.dataclass
class Kernel:
    """One kernel's resources (``spill_stores``/``spill_loads`` are None when the report has none)."""

    name: str
    registers: int
    stack: int
    spill_stores: int | None = None
    spill_loads: int | None = None

    @property
    def short(self) -> str:
        """The kernel's name without namespaces, template arguments and parameters (e.g. ``sample_kernel<d>``)."""
        match = re.search(r"([a-z][a-z_]*_kernel)(I([a-z])E)?", self.name)
        if not match:
            return self.name[:60]
        return match.group(1) + (f"<{match.group(3)}>" if match.group(3) else "")


def parse_ptxas(text: str) -> list[Kernel]:
    """The entry functions of a ``ptxas -v`` report."""
    kernels, stack, spills = [], 0, (0, 0)
    current = None
    for line in text.splitlines():
        if m := re.search(r"Compiling entry function '([^']+)'", line):
            current = m.group(1)
        elif m := re.search(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads", line):
            stack, spills = int(m.group(1)), (int(m.group(2)), int(m.group(3)))
        elif (m := re.search(r"Used (\d+) registers", line)) and current:
            kernels.append(Kernel(current, int(m.group(1)), stack, *spills))
            current = None
    return kernels


def parse_cuobjdump(text: str) -> list[Kernel]:
    """The functions of a ``cuobjdump --dump-resource-usage`` report (no spill counts there)."""
    kernels, name = [], None
    for line in text.splitlines():
        if m := re.search(r"Function ([^:\s]+):", line):
            name = m.group(1)
        elif (m := re.search(r"REG:(\d+) STACK:(\d+)", line)) and name:
            kernels.append(Kernel(name, int(m.group(1)), int(m.group(2))))
            name = None
    return kernels


def budget_of(kernel: Kernel) -> int:
    """The stack budget of ``kernel``."""
    return next((b for k, b in STACK_BUDGETS.items() if k in kernel.name), DEFAULT_STACK_BUDGET)


def violations(kernels: list[Kernel]) -> list[str]:
    """One line per kernel over its stack budget or spilling where it must not."""
    out = []
    for k in kernels:
        if k.stack > budget_of(k):
            out.append(f"{k.short}: {k.stack} bytes of stack, budget {budget_of(k)}")
        if any(n in k.name for n in NO_SPILLS) and (k.spill_stores or k.spill_loads):
            out.append(f"{k.short}: spills {k.spill_stores} bytes (stores), {k.spill_loads} (loads)")
    return out


def table(kernels: list[Kernel]) -> str:
    """The per-kernel table: registers, stack (and its budget), spill stores/loads."""
    rows = [f"{'kernel':<34} {'regs':>5} {'stack':>6} {'budget':>6} {'spill st/ld':>12}"]
    for k in sorted(kernels, key=lambda k: k.short):
        if "cub" in k.name.split("detail")[0]:
            continue
        spill = "-" if k.spill_stores is None else f"{k.spill_stores}/{k.spill_loads}"
        rows.append(f"{k.short:<34} {k.registers:>5} {k.stack:>6} {budget_of(k):>6} {spill:>12}")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    """Reads a report on stdin, prints the table; exit status 1 when a budget is exceeded."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--format", choices=("ptxas", "cuobjdump"), default="ptxas")
    args = parser.parse_args(argv)
    text = sys.stdin.read()
    kernels = parse_ptxas(text) if args.format == "ptxas" else parse_cuobjdump(text)
    if not kernels:
        print("kernel_resources: no kernel in the report", file=sys.stderr)
        return 1
    print(table(kernels))
    bad = violations(kernels)
    for line in bad:
        print(f"kernel_resources: over budget: {line}", file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

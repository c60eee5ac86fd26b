"""Compute levers for the stage-2 networks on this CPU: float32 eager against bfloat16 autocast (``neural.precision``)
and ``torch.compile``, for the U-Net shader and the PatchGAN discriminator at the shipped sizes.

A lever is worth shipping only if a training step gets cheaper (the step's other costs, the op, stay float32
either way). For each network the table gives the forward+backward seconds (the shipped config's batch, 2
threads; the median over ``--reps`` steps, float32 and bfloat16 interleaved step by step so that a change in the
machine's load hits both alike, with the CPU seconds beside the wall seconds), the one-off compile time and the
largest output difference against float32 eager. A lever that fails is a row with its error, not the end of the
run: eager levers catch their exceptions; ``torch.compile`` runs in a child process, so that a crash of inductor's
generated kernels (a signal) is caught too, and a child that does not answer within ``--compile-timeout`` seconds
is killed.

    python -m benchmarks.network_levers                  # both shipped sizes (default 64², lego 200²)
    python -m benchmarks.network_levers --sizes 64 --reps 20
    ONEDNN_MAX_CPU_ISA=AVX512_CORE python -m benchmarks.network_levers   # as on an AVX-512 CPU without BF16
    ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2 python -m benchmarks.network_levers   # as on an AVX2 CPU

Writes ``benchmarks/results/network_levers-<sizes>.json``, e.g. ``network_levers-64.json`` (with the machine
record, the CPU's native-bfloat16 features and what ``neural.precision: auto`` picks here). With the instruction
sets capped (:data:`ISA_CAPS`: the kernels of a lesser CPU, on this CPU's cores) it writes
``network_levers-<sizes>-<caps>.json`` naming the caps. (``network_levers.json`` is the record of an earlier
AVX2-only CPU, docs/history.md.)
"""
from __future__ import annotations

import argparse
import multiprocessing
import os
import signal
import statistics
import sys
import time
from multiprocessing.connection import Connection
from typing import Callable

import torch

from benchmarks.common import REPO, markdown, write_result
from nsplat.config import load_config, read_yaml
from nsplat.models import PatchDiscriminator, UNet
from nsplat.tasks.neural import precision
from nsplat.tasks.neural.config import Config

#: Image side → the shipped config whose networks run at it.
SIZES = {64: "default.yaml", 200: "lego.yaml"}
#: Environment variables that cap the instruction sets oneDNN and ATen's own kernels use.
ISA_CAPS = ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY")
#: Signals of a crash, given back their default action in the compiling child: a failure handler installed by an
#: imported library (glog's, through pycolmap) can deadlock in ``malloc`` after a heap corruption instead of ending it.
CRASH_SIGNALS = (signal.SIGSEGV, signal.SIGBUS, signal.SIGILL, signal.SIGFPE, signal.SIGABRT)
Step = Callable[[], torch.Tensor]


def _step(net: torch.nn.Module, args: tuple[torch.Tensor, ...], dtype: torch.dtype) -> Step:
    """One forward+backward of ``net`` on ``args`` in ``dtype`` (:func:`nsplat.tasks.neural.precision.autocast`);
    returns the
    float32 output."""

    def run() -> torch.Tensor:
        net.zero_grad(set_to_none=True)
        with precision.autocast(dtype, "cpu"):
            y = net(*args)
        y.float().square().mean().backward()
        return y.detach().float()

    return run


def _timed(step: Step) -> tuple[float, float]:
    w0, c0 = time.perf_counter(), time.process_time()
    step()
    return time.perf_counter() - w0, time.process_time() - c0


def _row(net: str, side: int, batch: int, lever: str, walls: list[float], cpus: list[float], diff: float | None,
         base: float | None, **extra: float) -> dict:
    """A measured lever: median wall and CPU seconds per step, its ratio to float32 eager's median ``base`` and its
    output's largest difference ``diff`` from float32 eager's (``None`` where float32 eager failed)."""
    wall = statistics.median(walls)
    return {"net": net, "side": side, "batch": batch, "lever": lever, "step_s": wall, "cpu_s": statistics.median(cpus),
            "step_s_min": min(walls), "reps": len(walls), "ratio": wall / base if base else None,
            "max_abs_diff": diff, **extra}


def _error(exc: Exception) -> str:
    """The exception's type and the first line of its message."""
    message = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {message[0] if message else ''}"[:300]


def _failed(net: str, side: int, batch: int, lever: str, error: str) -> dict:
    """A lever that failed: its row names the error."""
    return {"net": net, "side": side, "batch": batch, "lever": lever, "error": error}


def _networks(side: int) -> tuple[int, dict[str, tuple[torch.nn.Module, tuple[torch.Tensor, ...]]]]:
    """The batch of the shipped config at ``side`` and its two networks (seeded weights, channels-last) with their
    inputs: the same in every process."""
    n = load_config(Config, read_yaml(REPO / "configs" / SIZES[side])).neural
    C = n.features + int(n.alpha_input)  # the feature image the networks see
    g = torch.Generator().manual_seed(0)
    cond = torch.randn(n.batch, C, side, side, generator=g).contiguous(memory_format=torch.channels_last)
    rgb = torch.rand(n.batch, 3, side, side, generator=g).contiguous(memory_format=torch.channels_last)
    torch.manual_seed(0)
    unet, disc = UNet(C, 3, n.unet), PatchDiscriminator(C, 3, n.gan)
    return n.batch, {"unet": (unet.to(memory_format=torch.channels_last), (cond,)),
                     "discriminator": (disc.to(memory_format=torch.channels_last), (cond, rgb))}


def _eager(net: str, side: int, batch: int, model: torch.nn.Module, args: tuple[torch.Tensor, ...],
           reps: int) -> tuple[list[dict], float | None]:
    """float32 and bfloat16 eager, timed step by step in alternating order: ``(rows, float32 median seconds)``
    (``None`` where float32 failed)."""
    steps = {"float32 eager": _step(model, args, torch.float32), "bf16 autocast": _step(model, args, torch.bfloat16)}
    outs: dict[str, torch.Tensor] = {}
    failed: dict[str, str] = {}
    for lever, step in steps.items():
        try:
            outs[lever] = step()  # warm-up: oneDNN builds its kernels for these shapes
            step()
        except Exception as exc:  # noqa: BLE001 - a failed lever is a row
            failed[lever] = _error(exc)
    times: dict[str, tuple[list[float], list[float]]] = {lever: ([], []) for lever in outs}
    for k in range(reps):
        for lever in (list(times) if k % 2 == 0 else list(reversed(times))):
            wall, cpu = _timed(steps[lever])
            times[lever][0].append(wall)
            times[lever][1].append(cpu)
    ref = outs.get("float32 eager")
    base = statistics.median(times["float32 eager"][0]) if ref is not None else None
    rows = [_failed(net, side, batch, lever, failed[lever]) if lever in failed else
            _row(net, side, batch, lever, *times[lever], float((outs[lever] - ref).abs().max()) if ref is not None
                 else None, base) for lever in steps]
    return rows, base


def _compile_child(net: str, side: int, reps: int, conn: Connection) -> None:
    """In its own process: ``torch.compile`` of the float32 network; sends its output's difference from eager, the
    compile seconds and the timed steps, or the error."""
    for sig in CRASH_SIGNALS:
        signal.signal(sig, signal.SIG_DFL)
    torch.set_num_threads(2)
    try:
        _, nets = _networks(side)
        model, args = nets[net]
        ref = _step(model, args, torch.float32)()
        step = _step(torch.compile(model), args, torch.float32)
        t0 = time.perf_counter()
        out = step()
        compile_s = time.perf_counter() - t0
        walls, cpus = zip(*(_timed(step) for _ in range(reps)))
        conn.send({"diff": float((out - ref).abs().max()), "compile_s": compile_s, "walls": walls, "cpus": cpus})
    except Exception as exc:  # noqa: BLE001 - a failed lever is a row
        conn.send({"error": _error(exc)})


def _compiled(net: str, side: int, batch: int, reps: int, base: float, timeout_s: float) -> dict:
    """The ``torch.compile`` lever, run in a child process: an exception of the compiler, a crash of its
    generated kernels (a signal) and no answer within ``timeout_s`` seconds (the child is killed) alike become the
    row's error."""
    mp = multiprocessing.get_context("spawn")
    receive, send = mp.Pipe(duplex=False)
    proc = mp.Process(target=_compile_child, args=(net, side, reps, send))
    proc.start()
    send.close()
    if not receive.poll(timeout_s):
        proc.kill()
        proc.join()
        return _failed(net, side, batch, "torch.compile", f"no answer within {timeout_s:.0f} s (killed)")
    try:
        res = receive.recv()
    except EOFError:  # the child died before sending
        res = None
    proc.join()
    if res is None:
        code = proc.exitcode
        how = f"signal {signal.Signals(-code).name}" if code is not None and code < 0 else f"exit code {code}"
        return _failed(net, side, batch, "torch.compile", f"the compiling process died ({how})")
    if "error" in res:
        return _failed(net, side, batch, "torch.compile", res["error"])
    return _row(net, side, batch, "torch.compile", list(res["walls"]), list(res["cpus"]), res["diff"], base,
                compile_s=res["compile_s"])


def measure(side: int, reps: int, compile_reps: int, compile_timeout_s: float) -> list[dict]:
    """Every lever's row for both networks of the config at ``side`` (:func:`_eager`, :func:`_compiled`)."""
    batch, nets = _networks(side)
    rows = []
    for name, (model, args) in nets.items():
        eager, base = _eager(name, side, batch, model, args, reps)
        rows += eager
        if base is not None and compile_reps > 0:
            rows.append(_compiled(name, side, batch, compile_reps, base, compile_timeout_s))
        print(f"{name} {side}² done", file=sys.stderr, flush=True)
    return rows


def _cell(r: dict, key: str, fmt: str) -> str:
    return format(r[key], fmt) if r.get(key) is not None else "–"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", nargs="+", type=int, default=sorted(SIZES), choices=sorted(SIZES))
    p.add_argument("--reps", type=int, default=20, help="timed steps per eager lever (interleaved)")
    p.add_argument("--compile-reps", type=int, default=5, help="timed steps of the compiled network (0: skip it)")
    p.add_argument("--compile-timeout", type=float, default=900.0,
                   help="seconds the compiling child may take (compile and timed steps) before it is killed")
    args = p.parse_args()
    torch.set_num_threads(2)
    load = os.getloadavg()
    caps = precision.cpu_capabilities()
    dtype, why = precision.auto_dtype(torch.device("cpu"), caps)
    auto = str(dtype).removeprefix("torch.")
    capped = {k: os.environ[k] for k in ISA_CAPS if os.environ.get(k)}
    rows = [r for side in args.sizes for r in measure(side, args.reps, args.compile_reps, args.compile_timeout)]
    table = markdown(["net", "side", "batch", "lever", "fwd+bwd s (median)", "CPU s", "× float32", "max |Δ| vs float32",
                      "compile s", "error"],
                     [[r["net"], r["side"], r["batch"], r["lever"], _cell(r, "step_s", ".4f"), _cell(r, "cpu_s", ".4f"),
                       _cell(r, "ratio", ".2f"), _cell(r, "max_abs_diff", ".1e"), _cell(r, "compile_s", ".0f"),
                       r.get("error", "")] for r in rows])
    print(f"CPU capability {torch.backends.cpu.get_cpu_capability()}, native bfloat16: "
          f"{[f for f in precision.NATIVE_BF16 if f in caps] or 'none'}; neural.precision auto -> {auto} "
          f"({why}; from the "
          f"CPU's flags, whatever the caps); "
          f"2 threads, load before {load[0]:.2f}, after {os.getloadavg()[0]:.2f}"
          + "".join(f"; {k}={v}" for k, v in capped.items()))
    name = "-".join(["network_levers", *map(str, args.sizes), *(v.lower() for v in capped.values())])
    write_result(name, {"isa_caps": capped, "capability": torch.backends.cpu.get_cpu_capability(),
                        "native_bf16": [f for f in precision.NATIVE_BF16 if f in caps], "auto": auto, "threads": 2,
                        "reps": args.reps, "compile_reps": args.compile_reps, "compile_timeout_s": args.compile_timeout,
                        "load_before": load, "load_after": list(os.getloadavg()), "rows": rows},
                 table)


if __name__ == "__main__":
    main()

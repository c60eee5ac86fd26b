"""Compute levers for the stage-2 networks on this CPU: float32 eager against bfloat16 autocast
and ``torch.compile``, for the U-Net shader and the PatchGAN discriminator at the shipped sizes.

A lever is worth shipping only if a training step gets cheaper (the step's other costs, the op, stay
float32 either way). The table gives the forward+backward seconds of each network (batch 2, 2 threads),
the one-off compile time, and the largest output difference against float32 eager.

    python -m benchmarks.network_levers                  # both shipped sizes (default 64², lego 200²)
    python -m benchmarks.network_levers --sizes 64 --reps 5

Writes ``benchmarks/results/network_levers.json`` (with the CPU capability and the load average).
"""
from __future__ import annotations

import argparse
import os
import time

import torch

from benchmarks.common import REPO, write_result
from nsplat.config import load_config, read_yaml
from nsplat.models import PatchDiscriminator, UNet
from nsplat.tasks.neural.config import Config

#: Image side → the shipped config whose networks run at it.
SIZES = {64: "default.yaml", 200: "lego.yaml"}


def _step(net: torch.nn.Module, args: tuple[torch.Tensor, ...], bf16: bool) -> torch.Tensor:
    net.zero_grad(set_to_none=True)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        y = net(*args)
    y.float().square().mean().backward()
    return y.detach().float()


def _time(net: torch.nn.Module, args: tuple[torch.Tensor, ...], bf16: bool, reps: int) -> tuple[float, torch.Tensor]:
    out = _step(net, args, bf16)  # warm-up (and, compiled, the compilation)
    t0 = time.perf_counter()
    for _ in range(reps):
        _step(net, args, bf16)
    return (time.perf_counter() - t0) / reps, out


def measure(side: int, reps: int) -> list[dict]:
    n = load_config(Config, read_yaml(REPO / "configs" / SIZES[side])).neural
    C = n.features + int(n.alpha_input)  # the feature image the networks see
    g = torch.Generator().manual_seed(0)
    cond = torch.randn(2, C, side, side, generator=g).contiguous(memory_format=torch.channels_last)
    rgb = torch.rand(2, 3, side, side, generator=g).contiguous(memory_format=torch.channels_last)
    nets = {"unet": (UNet(C, 3, n.unet), (cond,)), "discriminator": (PatchDiscriminator(C, 3, n.gan), (cond, rgb))}
    rows = []
    for name, (net, args) in nets.items():
        net = net.to(memory_format=torch.channels_last)
        base, ref = _time(net, args, False, reps)
        half, out = _time(net, args, True, reps)
        t0 = time.perf_counter()
        compiled = torch.compile(net)
        _step(compiled, args, False)
        compile_s = time.perf_counter() - t0
        comp, cout = _time(compiled, args, False, reps)
        for lever, sec, o, extra in (("float32 eager", base, ref, {}), ("bf16 autocast", half, out, {}),
                                     ("torch.compile", comp, cout, {"compile_s": compile_s})):
            rows.append({"net": name, "side": side, "lever": lever, "step_s": sec, "ratio": sec / base,
                         "max_abs_diff": float((o - ref).abs().max()), **extra})
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", nargs="*", type=int, default=sorted(SIZES), choices=sorted(SIZES))
    p.add_argument("--reps", type=int, default=3)
    args = p.parse_args()
    torch.set_num_threads(2)
    load = os.getloadavg()
    rows = [r for side in args.sizes for r in measure(side, args.reps)]
    print(f"CPU capability {torch.backends.cpu.get_cpu_capability()}, 2 threads, load before {load[0]:.2f}, "
          f"after {os.getloadavg()[0]:.2f}")
    print("| net | side | lever | fwd+bwd s | × float32 | max |Δ| vs float32 | compile s |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['net']} | {r['side']} | {r['lever']} | {r['step_s']:.3f} | {r['ratio']:.2f} | "
              f"{r['max_abs_diff']:.2e} | {r.get('compile_s', float('nan')):.0f} |")
    write_result("network_levers", {"capability": torch.backends.cpu.get_cpu_capability(), "threads": 2,
                                    "load_before": load, "rows": rows})


if __name__ == "__main__":
    main()

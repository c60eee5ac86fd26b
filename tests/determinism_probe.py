"""Child process of ``test_op_is_bitwise_identical_across_threads_and_cpu_capabilities``: renders the
scene saved in ``argv[1]`` with ``deterministic=True`` at 1, 2 and 3 threads and prints, per thread
count, a JSON object of SHA-1 digests of every output and gradient. Run under a chosen
``ATEN_CPU_CAPABILITY`` by the test; the inputs come from a file so that they are the same bits in
every process (ATen's random generators themselves differ between capabilities)."""
from __future__ import annotations

import hashlib
import json
import sys

import torch

from nsplat.ops import splat


def digest(t: torch.Tensor) -> str:
    return hashlib.sha1(t.detach().contiguous().numpy().tobytes()).hexdigest()


def run(path: str) -> dict[str, dict[str, str]]:
    case = torch.load(path)
    out: dict[str, dict[str, str]] = {}
    for threads in (1, 2, 3):
        torch.set_num_threads(threads)
        for est, comp in (("ht", "alpha"), ("paper", "additive"), ("sampled", "alpha")):
            leaves = [case[k].clone().requires_grad_() for k in ("means", "normals", "scales", "opacities",
                                                                 "features", "viewmats")]
            bg = case["background"].clone().requires_grad_()
            o = splat(*leaves, case["Ks"], case["width"], case["height"], samples=12, estimator=est, composite=comp,
                      background=bg, seed=5, deterministic=True)
            loss = (o.image * case["wi"]).sum() + (o.alpha * case["wa"]).sum() + (o.depth * case["wd"]).sum()
            grads = torch.autograd.grad(loss, leaves + [bg])
            names = ("means", "normals", "scales", "opacities", "features", "viewmats", "background")
            out[f"{threads}/{est}/{comp}"] = {
                **{k: digest(getattr(o, k)) for k in ("image", "alpha", "depth", "probs", "indices", "total")},
                **{f"grad_{n}": digest(g) for n, g in zip(names, grads)}}
    return out


if __name__ == "__main__":
    print(json.dumps({"capability": torch.backends.cpu.get_cpu_capability(), "digests": run(sys.argv[1])}))

"""Small CUDA workloads for ``compute-sanitizer`` (not a pytest module: run it under the sanitizer).

    compute-sanitizer --tool memcheck --error-exitcode 9 python tests/cuda_sanitizer_case.py all
    compute-sanitizer --tool racecheck --error-exitcode 9 python tests/cuda_sanitizer_case.py one

``all`` launches every kernel path of the op once on tiny scenes: both compositing modes, the three gradient
estimators, float32 and float64, a sample larger than any shared-memory heap (samples=300), many channels
(the chunked per-point feature pass), Hermite order 0 (exact leaf sums only), batched cameras, the tree on
N=0 and N < samples, the non-deterministic (atomic) accumulation and stratified sampling. ``one`` is a single
alpha/``ht`` forward+backward (racecheck is slow).
Prints one line per case; the sanitizer's own summary says whether any access was bad.
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nsplat.ops import splat  # noqa: E402
from tests.conftest import make_cameras, make_scene  # noqa: E402

CUDA = torch.device("cuda")
PARAMS = ("means", "normals", "scales", "opacities", "features")


def run_case(N: int, C: int, B: int, W: int, H: int, dtype: torch.dtype, **kw) -> None:
    """One forward + backward on CUDA of ``N`` random surfels, ``C`` channels, ``B`` cameras of ``W``×``H``."""
    sc = make_scene(N, seed=N + C, C=C, dtype=dtype)
    V, K = make_cameras(B, W, H, dtype=dtype)
    ps = [sc[n].to(CUDA).requires_grad_() for n in PARAMS]
    bg = torch.full((C,), 0.5, dtype=dtype, device=CUDA, requires_grad=True)
    out = splat(*ps, V.to(CUDA), K.to(CUDA), W, H, background=bg, **kw)
    loss = out.image.square().sum() + out.alpha.sum() + out.depth.sum()
    grads = torch.autograd.grad(loss, ps + [bg], allow_unused=True)
    torch.cuda.synchronize()
    finite = all(g is None or bool(torch.isfinite(g).all()) for g in grads)
    print(f"N={N} C={C} B={B} {W}x{H} {dtype} {kw}: image sum {float(out.image.detach().sum()):.6g}, "
          f"finite grads {finite}",
          flush=True)


def main(which: str) -> int:
    if not torch.cuda.is_available():
        print("cuda_sanitizer_case: no CUDA device")
        return 2
    if which == "one":
        run_case(200, 3, 1, 24, 20, torch.float32, samples=8, composite="alpha", estimator="ht", seed=1)
        return 0
    for composite in ("alpha", "additive"):
        for estimator in ("ht", "paper", "sampled"):
            for dtype in (torch.float32, torch.float64):
                run_case(300, 3, 2, 32, 24, dtype, samples=8, composite=composite, estimator=estimator, seed=2)
    run_case(400, 3, 1, 20, 16, torch.float32, samples=300, seed=3)
    run_case(50, 33, 3, 8, 8, torch.float64, samples=200, seed=4)
    run_case(2000, 3, 1, 40, 32, torch.float32, samples=8, hermite_order=0, seed=5)
    run_case(0, 3, 2, 9, 7, torch.float32, samples=5, seed=6)
    run_case(3, 3, 2, 9, 7, torch.float32, samples=5, seed=7)
    run_case(300, 3, 2, 32, 24, torch.float32, samples=8, deterministic=False, seed=8)
    run_case(300, 3, 2, 32, 24, torch.float32, samples=8, stratified=True, seed=9)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else "all"))

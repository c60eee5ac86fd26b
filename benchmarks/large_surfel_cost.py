"""What the few largest surfels cost the sampler: why stage-1 steps slow down as a fit converges.

For each fitted scene (a neural run's ``geometry.ply``) renders 10 training views (every 6th) with the op, after
one warm-up render, keeping every surfel or only those whose larger tangent std is below each ``--caps``
value (world units), and reports the render time per view, the sampler's exact kernel evaluations per
pixel (the op's ``work``) and where the evaluations the large surfels add go: the share of them made at pixels
that are empty (total size measure below the op's floor) once those surfels are removed, i.e. background
pixels reached only by the tails of the large kernels.

    python train.py --config configs/lego_splat_only.yaml --run runs/lego_splat_only   # the surfels (30 min)
    python train.py --config configs/lego_splat_only.yaml --run runs/lego_nocap geometry.optim.max_scale=0
    python -m benchmarks.large_surfel_cost runs/lego_nocap/geometry.ply runs/lego_splat_only/geometry.ply

Prints a table and writes ``benchmarks/results/large_surfel_cost.json``.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from benchmarks.common import REPO as ROOT
from benchmarks.common import write_result
from benchmarks.fitted import load_fitted
from nsplat.render import render
from nsplat.sh import view_colour


def measure(ply: str, config: str, caps: list[float]) -> list[dict]:
    fitted = load_fitted(config, ply, splits=("train",))
    cfg, views, scene = fitted.cfg, fitted.train, fitted.load()
    largest = scene.scales.detach().max(1).values
    median = float(largest.median())
    rows = []
    picked = range(0, len(views), max(1, len(views) // 10))
    full_work: dict[int, torch.Tensor] = {}  # per view, with every surfel kept
    with torch.no_grad():
        for cap in [float("inf"), *caps]:
            keep = largest < cap
            means, feats = scene.means[keep], scene.features[keep]
            args = (scene.normals[keep], scene.scales[keep], scene.opacities[keep])

            def one(v: int) -> tuple[torch.Tensor, torch.Tensor]:
                f = view_colour(feats, means, views.viewmats[v])
                out = render(means, *args, f, views.viewmats[v:v + 1], views.Ks[v:v + 1], views.width,
                             views.height, cfg.render, seed=v)
                return out.work.double(), out.total

            one(0)  # warm-up
            seconds, work, extra, extra_empty = 0.0, 0.0, 0.0, 0.0
            for v in picked:
                t0 = time.perf_counter()
                w, total = one(v)
                seconds += time.perf_counter() - t0
                work += float(w.mean())
                if cap != float("inf"):  # the evaluations the removed surfels added, and where
                    more = full_work[v] - w
                    extra += float(more.sum())
                    extra_empty += float(more[total == 0].sum())
                else:
                    full_work[v] = w
            rows.append({"ply": ply, "cap": cap, "cap_over_median": cap / median, "kept": int(keep.sum()),
                         "removed": int((~keep).sum()), "ms_per_view": 1000.0 * seconds / len(picked),
                         "work_per_pixel": work / len(picked),
                         "extra_share_at_empty_pixels": extra_empty / extra if extra > 0 else None})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("plys", nargs="+")
    ap.add_argument("--config", default=str(ROOT / "configs" / "lego.yaml"))
    ap.add_argument("--caps", type=float, nargs="+", default=[0.05, 0.03, 0.02])
    args = ap.parse_args()
    rows = [r for ply in args.plys for r in measure(ply, args.config, args.caps)]
    print("| scene | kept if largest std < | surfels removed | render ms / view | kernel evaluations / pixel | "
          "share of the removed surfels' evaluations at pixels then empty |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        cap = "all kept" if r["cap"] == float("inf") else f"{r['cap']:g} ({r['cap_over_median']:.1f}× median)"
        share = "" if r["extra_share_at_empty_pixels"] is None else f"{100 * r['extra_share_at_empty_pixels']:.1f} %"
        print(f"| {Path(r['ply']).parent.name} | {cap} | {r['removed']} | {r['ms_per_view']:.0f} | "
              f"{r['work_per_pixel']:.1f} | {share} |")
    write_result("large_surfel_cost", {"config": args.config,
                                       "rows": [{**r, "cap": str(r["cap"])} for r in rows]})


if __name__ == "__main__":
    main()

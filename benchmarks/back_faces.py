"""Where a fitted stage 1's samples go, and what more samples at evaluation do.

Loads fitted surfels (default: ``runs/lego_splat_only/geometry.ply``, configs/lego_splat_only.yaml's stage 1;
two-sided surfels) and, on the first
``--views`` val views, draws each pixel's sample with the config's render settings: on object pixels (alpha
> 0.5) it reports how many of the m slots are filled, the share of filled slots that hold **back faces**
(surfels whose normal faces away from the camera) and the share of the composite weight they carry, and the
kernel evaluations per pixel. Then the val PSNR (every val view, the evaluation's draws) with the evaluation
rendered at each ``--samples`` value (``eval.render.samples``) instead of the m the surfels were fitted with.

    python train.py --config configs/lego_splat_only.yaml --run runs/lego_splat_only   # the surfels (30 min)
    python -m benchmarks.back_faces runs/lego_splat_only/geometry.ply

Prints two tables and writes ``benchmarks/results/back_faces.json``.
"""
from __future__ import annotations

import argparse

import torch

from benchmarks.common import REPO as ROOT
from benchmarks.common import write_result
from benchmarks.fitted import load_fitted, val_psnr
from nsplat.config import load_config, read_yaml
from nsplat.ops import splat
from nsplat.tasks.neural.config import Config


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("ply", nargs="?", default=str(ROOT / "runs" / "lego_splat_only" / "geometry.ply"))
    ap.add_argument("--config", default=str(ROOT / "configs" / "lego.yaml"))
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--samples", type=int, nargs="+", default=[40, 64, 96, 160])
    args = ap.parse_args()
    fitted = load_fitted(args.config, args.ply, splits=("val",))
    cfg, val, scene = fitted.cfg, fitted.val, fitted.load()
    r = cfg.render
    kw = dict(samples=r.samples, eps=r.eps, lowpass=r.lowpass, estimator=r.estimator, near=r.near, far=r.far)
    print(f"{args.ply}: {scene.num_points} surfels, m = {r.samples}")
    print("| val view | object px | filled slots | back-face share of slots | of composite weight | evaluations/px |")
    print("|---|---|---|---|---|---|")
    views = []
    with torch.no_grad():
        means, normals = scene.means, scene.normals
        for v in range(min(args.views, len(val))):
            vm, K = val.viewmats[v:v + 1], val.Ks[v:v + 1]
            eye = -vm[0, :3, :3].T @ vm[0, :3, 3]
            back = ((eye - means) * normals).sum(-1) <= 0
            out = splat(means, normals, scene.scales, scene.opacities, back.to(means.dtype)[:, None], vm, K,
                        val.width, val.height, seed=v, **kw)
            obj = out.alpha[0, ..., 0] > 0.5
            idx = out.indices[0].long()
            filled = idx >= 0
            back_slots = back[idx.clamp_min(0)] & filled
            row = {"view": v, "object_px": int(obj.sum()), "filled": float(filled[obj].sum(-1).float().mean()),
                   "back_slot_share": float(back_slots[obj].sum() / filled[obj].sum()),
                   "back_weight_share": float((out.image[0, ..., 0] / out.alpha[0, ..., 0])[obj].mean()),
                   "evaluations": float(out.work[0, ..., 0][obj].float().mean())}
            views.append(row)
            print(f"| {v} | {row['object_px']} | {row['filled']:.1f} / {r.samples} | {row['back_slot_share']:.2f} | "
                  f"{row['back_weight_share']:.2f} | {row['evaluations']:.0f} |", flush=True)
    print("\n| evaluation m | val PSNR |\n|---|---|")
    psnrs = []
    for m in args.samples:
        cfg_m = load_config(Config, read_yaml(args.config), [f"eval.render={{samples: {m}}}"])
        p = val_psnr(scene, cfg_m, val)
        psnrs.append({"samples": m, "val_psnr": p})
        print(f"| {m} | {p:.2f} |", flush=True)
    write_result("back_faces", {"ply": args.ply, "config": args.config, "fit_samples": r.samples, "views": views,
                                "eval_samples": psnrs})


if __name__ == "__main__":
    main()

"""How close does a 3DGS renderer come to nsplat's own render of a ``export --format 3dgs`` file, and nsplat to the
3DGS render of a file it imports?

For a run's stage-1 surfels (``RUN/geometry.ply``), on the held-out views of its config:

* ``nsplat``: the op's render (evaluation settings and draws), the run's own stage-1 score;
* ``3dgs classic: converted``: ``export --format 3dgs --fit-epochs 0`` (the kernel conversion alone, κ̄ over the
  training cameras) in the 3DGS reference renderer (:mod:`tests.gs_reference`: 3DGS's image formation,
  gsplat's 0.999 clamp, centre-depth order);
* ``3dgs classic: fitted``: ``export --format 3dgs --fit-epochs N`` (the conversion, then N epochs of fitting
  to nsplat's renders of the training cameras, :mod:`nsplat.gaussians.fit`) in the same renderer;
* ``3dgs antialiased``: ``export --format 3dgs --antialiased`` in the reference renderer's antialiased mode
  (Mip-Splatting's compensation, which the file's header asks for);
* ``nsplat: import …``: each file read back as stage 1's start (``geometry.init: ply``) rendered by nsplat.

Each row: PSNR against the ground truth and against nsplat's render (mean over views). Usage::

    python train.py --run runs/default                    # or any run with a geometry.ply
    python -m benchmarks.export_fidelity --run runs/default --fit-epochs 3
    NSPLAT_DATA=... python train.py --config configs/lego_splat_only.yaml --run runs/lego12 \\
        geometry.optim.epochs=12 geometry.optim.anneal_epochs=2
    NSPLAT_DATA=... python -m benchmarks.export_fidelity --run runs/lego12 --fit-epochs 3

Settings are chosen with ``--split val``; the reported figures are ``--split test``. Writes
``benchmarks/results/export_fidelity-<run folder name>[-<split>].json``.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import torch
import yaml

from benchmarks.common import markdown, write_result
from nsplat.config import load_config
from nsplat.evaluation.image_metrics import psnr
from nsplat.gaussians.export import export
from nsplat.gaussians.fit import FitSettings
from nsplat.render.renderer import render_views
from nsplat.scene import SurfelScene
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.data import load_views
from nsplat.tasks.neural.starts import geometry_scene_config, initial_geometry
from nsplat.viewer.runs import load_run
from tests.gs_reference import gaussians_of_ply, render_3dgs


def reference_images(path: Path, views) -> torch.Tensor:
    """The reference renderer's images ``[B,H,W,3]`` of the 3DGS file ``path`` from ``views``, in the mode its
    header names."""
    g = gaussians_of_ply(str(path))
    return torch.stack([render_3dgs(g["means"], g["quats"], g["log_scales"], g["opacity_logits"], g["sh"],
                                    views.viewmats[i], views.Ks[i], views.width, views.height, views.background,
                                    antialiased=g["antialiased"])
                        for i in range(len(views))]).float().clamp(0, 1)


def nsplat_images(scene: SurfelScene, cfg: Config, views) -> torch.Tensor:
    """nsplat's evaluation render ``[B,H,W,3]`` of ``scene`` (the settings and seeds of ``evaluate_geometry``)."""
    seed = cfg.eval_seed()
    return torch.cat([render_views(scene, views.viewmats[s:s + 4], views.Ks[s:s + 4], views.width, views.height,
                                   cfg.eval_render(), seed=seed + s, shading=cfg.geometry.optim.shading,
                                   background=views.background, draws=cfg.eval.draws)
                      for s in range(0, len(views), 4)]).float().clamp(0, 1)


@torch.no_grad()
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, required=True, help="run folder with a geometry.ply (stage 1 finished)")
    ap.add_argument("--split", default="test", help="held-out split (default: test)")
    ap.add_argument("--views", type=int, default=0, help="first N views of the split only (0: all)")
    ap.add_argument("--fit-epochs", type=int, default=FitSettings().epochs, help="epochs of the fitted classic file")
    args = ap.parse_args()
    raw = yaml.safe_load((args.run / "config.yaml").read_text())
    cfg = load_config(Config, raw)
    cpu = torch.device("cpu")
    views = load_views(cfg, args.split, cpu)
    if args.views:
        views = dataclasses.replace(views, images=views.images[:args.views], viewmats=views.viewmats[:args.views],
                                    Ks=views.Ks[:args.views], names=views.names[:args.views])
    scene = SurfelScene.load_ply(args.run / "geometry.ply", geometry_scene_config(cfg), device=cpu)
    gt = views.images.float()
    rows, record, timing = [], {}, {}

    def add(name: str, img: torch.Tensor, ref: torch.Tensor | None) -> None:
        p_gt = psnr(img, gt).double()
        p_ref = psnr(img, ref).double() if ref is not None else None
        record[name] = {"psnr_gt": float(p_gt.mean()), "psnr_gt_per_view": p_gt.tolist(),
                        "psnr_vs_nsplat": None if p_ref is None else float(p_ref.mean())}
        rows.append([name, f"{float(p_gt.mean()):.2f}", "—" if p_ref is None else f"{float(p_ref.mean()):.2f}"])
        print(rows[-1], flush=True)

    t0 = time.perf_counter()
    ours = nsplat_images(scene, cfg, views)
    timing["nsplat_s"] = time.perf_counter() - t0
    add("nsplat", ours, None)
    files = {"3dgs classic: converted": {"fit": FitSettings(epochs=0)},
             f"3dgs classic: fitted ({args.fit_epochs} epochs)": {"fit": FitSettings(epochs=args.fit_epochs)},
             "3dgs antialiased": {"antialiased": True}}
    with tempfile.TemporaryDirectory() as tmp:
        for i, (name, kw) in enumerate(files.items()):
            t0 = time.perf_counter()
            path = export(load_run(args.run, cpu, points=True), "3dgs", Path(tmp) / f"{i}.ply", **kw)
            timing[f"export_s: {name}"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            add(name, reference_images(path, views), ours)
            timing[f"reference_s: {name}"] = time.perf_counter() - t0
            files[name] = path
        for name in ("3dgs classic: converted", "3dgs antialiased"):
            raw_import = {**raw, "geometry": {**raw["geometry"], "init": "ply", "ply": str(files[name])}}
            icfg = load_config(Config, raw_import)
            imported = initial_geometry(icfg, load_views(icfg, "train", cpu), seed=0)
            add(f"nsplat: import of {name}", nsplat_images(imported, cfg, views), ours)
    header = ["render", f"PSNR vs ground truth ({args.split}, dB)", "PSNR vs nsplat (dB)"]
    table = markdown(header, rows)
    suffix = "" if args.split == "test" else f"-{args.split}"
    write_result(f"export_fidelity-{args.run.name}{suffix}", {
        "command": "python -m benchmarks.export_fidelity " + " ".join(sys.argv[1:]),
        "run": str(args.run), "split": args.split, "views": len(views), "points": scene.num_points,
        "resolution": [views.width, views.height], "lowpass": cfg.eval_render().lowpass,
        "samples": cfg.eval_render().samples, "draws": cfg.eval.draws, "fit": dataclasses.asdict(
            FitSettings(epochs=args.fit_epochs)), "results": record, "timing_s": timing,
        "geometry_epochs": cfg.geometry.optim.epochs}, table)


if __name__ == "__main__":
    main()

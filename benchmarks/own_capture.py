"""Your own capture, measured: SfM poses and points against ground-truth poses and the visual hull.

The procedural scene is photographed in front of a textured environment through a distorted OPENCV camera
(256², 56 photos, no masks used) and reconstructed by pycolmap's SfM on the CPU
(:mod:`nsplat.data.synthetic_capture`; its time is in the capture's ``sfm.json``). Then ``configs/colmap.yaml``
trains on it at ``downscale`` 4 (64², like the main job), every 8th photo by name held out as test and every
8th of the rest as val, two ways:

* ``sfm``: SfM poses and the SfM-point start (``geometry.init: sfm``) with the background sphere fitted to the
  distant SfM points: the one-command path a user gets (``configs/colmap.yaml`` as shipped);
* ``gt-hull``: the same photos with the ground-truth cameras (``sparse_gt/0``, undistorted with the true
  distortion), the visual hull of the true object masks (``masks/``) and the background sphere on the true
  environment (there are no SfM points to place it by): the same recipe, ground truth throughout.

    python -m benchmarks.own_capture                 # the capture, SfM and both runs (about 30 min on 2 cores)
    python -m benchmarks.own_capture --only sfm      # one run, no report

Writes ``benchmarks/results/own_capture.json``, draws ``docs/images/neural/own_capture.png`` and prints a
Markdown table. The study that chose the recipe (background model, random fill, stage-1 levers) ran at
commit 5a3af74 (``benchmarks/own_capture.py`` there; docs/history.md).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import pycolmap
from matplotlib.figure import Figure

from benchmarks.common import IMAGES, REPO, run_config, write_result
from benchmarks.neural_runs import save, summary, view_grid
from nsplat.data.synthetic_capture import CaptureSpec, ensure_capture

SPEC = CaptureSpec(resolution=256, views=56)


def sfm_accuracy(capture: Path) -> dict[str, float]:
    """SfM cameras against the truth after the best similarity of the camera centres: centre error (world
    units; cameras are ``SPEC.radius`` from the scene), rotation error (degrees), focal length and k1."""
    est, gt = (pycolmap.Reconstruction(str(capture / m)) for m in ("sparse/0", "sparse_gt/0"))
    e, g = ({im.name: im for im in r.images.values()} for r in (est, gt))
    names = sorted(g)
    sim = pycolmap.estimate_sim3d(np.array([e[n].projection_center() for n in names]),
                                  np.array([g[n].projection_center() for n in names]))
    err = [np.linalg.norm(sim.matrix() @ np.append(e[n].projection_center(), 1) - g[n].projection_center())
           for n in names]
    ang = []
    for n in names:
        dR = (e[n].cam_from_world().rotation.matrix() @ sim.rotation.matrix().T
              @ g[n].cam_from_world().rotation.matrix().T)
        ang.append(math.degrees(math.acos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    cam, true = next(iter(est.cameras.values())), SPEC.camera()
    return {"registered": len(e), "centre_error_mean": float(np.mean(err)), "centre_error_max": float(max(err)),
            "rotation_error_mean_deg": float(np.mean(ang)), "rotation_error_max_deg": float(max(ang)),
            "focal": float(cam.focal_length_x), "focal_true": float(true.focal_length_x),
            "k1": float(cam.params[4]), "k1_true": float(true.params[4])}


#: The true environment sphere in the ground-truth training frame (the normalisation moves the cameras'
#: look-at point (0, 0, 0.3) to the origin and keeps the scale: the cameras are ``SPEC.radius`` from it).
GT_ENVIRONMENT = [f"geometry.background.radius={SPEC.environment / SPEC.radius}",
                  "geometry.background.centre=[0.0,0.0,-0.3]"]
#: Overrides of ``configs/colmap.yaml`` per run.
VARIANTS: dict[str, list[str]] = {
    "sfm": [],
    "gt-hull": ["data.capture.sparse=sparse_gt/0", "data.capture.masks=masks", "geometry.init=hull", *GT_ENVIRONMENT],
}


def train(capture: Path, run: Path, overrides: list[str]) -> float:
    """One training run (skipped when it already evaluated); returns its wall time in seconds."""
    if (run / "eval_test" / "metrics.json").is_file():
        return float("nan")
    ran = run_config(REPO / "configs" / "colmap.yaml", run,
                     [f"data.root={capture}", "data.capture.downscale=4", "log.progress=false", *overrides])
    return ran["wall_s"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=Path, default=REPO / "runs" / "own_capture")
    ap.add_argument("--cache", type=Path, default=REPO / "data_cache")
    ap.add_argument("--only", nargs="+", choices=sorted(VARIANTS), help="run only these variants, no report")
    args = ap.parse_args()
    capture = ensure_capture(SPEC, args.cache)
    if args.only:
        for name in args.only:
            print(f"{name}: {train(capture, args.runs / name, VARIANTS[name]):.0f} s", flush=True)
        return
    sfm = {**json.loads((capture / "sfm.json").read_text()), **sfm_accuracy(capture)}
    walls = {name: train(capture, args.runs / name, overrides) for name, overrides in VARIANTS.items()}
    rows = {name: summary(name, args.runs / name, "test") for name in VARIANTS}
    lines = ["| run | points | stage 1 alone val / test PSNR | val PSNR (last) | test PSNR | test SSIM | train s |",
             "|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        g, m = r["geometry"], r["test"]
        lines.append(f"| {name} | {m['points']} | {g['val']['psnr']['mean']:.2f} / {g['test']['psnr']['mean']:.2f} | "
                     f"{r['history'][-1]['val_psnr']:.2f} | {m['psnr']['mean']:.2f} ± {m['psnr']['std']:.2f} | "
                     f"{m['ssim']['mean']:.4f} | {r['timing']['train_total_s']:.0f} |")
    text = "\n".join(lines)
    gap = rows["gt-hull"]["test"]["psnr"]["mean"] - rows["sfm"]["test"]["psnr"]["mean"]
    write_result("own_capture", {
        "command": "python -m benchmarks.own_capture " + " ".join(sys.argv[1:]), "capture": str(capture),
        "spec": json.loads((capture / "spec.json").read_text()), "sfm": sfm, "variants": VARIANTS, "walls_s": walls,
        "test_psnr_gap_gt_minus_sfm_db": gap,
        "runs": {k: {kk: vv for kk, vv in r.items() if kk != "per_view"} for k, r in rows.items()}, "markdown": text},
        text)
    fig = Figure(figsize=(13, 12))
    for panel, name in zip(fig.subfigures(2, 1), VARIANTS):
        view_grid(panel, Path(rows[name]["run"]), rows[name]["per_view"][:4], "test", rows=3)
        panel.suptitle(f"{name}: test {rows[name]['test']['psnr']['mean']:.2f} dB", fontsize=10)
    save(fig, IMAGES / "neural" / "own_capture.png",
         f"Own capture (pycolmap SfM {sfm['total_s']:.0f} s): SfM vs ground truth")
    print(f"SfM: {sfm}\ntest PSNR gap (gt-hull − sfm): {gap:.2f} dB")


if __name__ == "__main__":
    main()

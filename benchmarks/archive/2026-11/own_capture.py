"""Your own capture, measured (issue 26): SfM poses and points against ground-truth poses and the visual hull.

The procedural scene is photographed in front of a textured environment through a distorted OPENCV camera
(256², 56 photos, no masks used) and reconstructed by pycolmap's SfM on the CPU
(:mod:`nsplat.data.synthetic_capture`; its time is in the capture's ``sfm.json``). Then
``configs/colmap.yaml`` trains on it at ``downscale`` 4 (64², like the main job), every 8th photo by name
held out as test and every 8th of the rest as val:

* ``sfm``: SfM poses, SfM-point initialisation (``geometry.init: sfm``), background sphere (radius from the
  SfM points): the one-command path a user gets;
* ``gt-hull``: the same photos with the ground-truth cameras (``sparse_gt/0``, undistorted with the true
  distortion) and the visual-hull initialisation from the true object masks (``masks/``), the background
  sphere on the true environment (there are no SfM points to place it by);
* background model (stage 1 alone, ``neural.steps=0``, chosen on val): ``sphere`` (with the scene's SfM
  points, the shipped ``geometry.sfm.background_points: false``, or with all of them) vs ``none`` (only the
  constant ``data.background``, all SfM points) with the SfM start;
* closing the gap (``GAP``, stage 1 alone, chosen on val): densification, the random fill
  (``geometry.sfm.fill``), the lego stage-1 levers, at 8 epochs against the same baseline, then the winner
  at 20 epochs. Every run here but the winner's starts from ``BEFORE``, the recipe before that study.

    python benchmarks/own_capture.py                 # runs what is missing under runs/own_capture/, then reports
    python benchmarks/own_capture.py --only s8-base  # runs just these variants, no report

Writes ``benchmarks/results/own_capture.json``, draws ``docs/images/neural/own_capture.png`` and prints a
Markdown table. Each run is ``python train.py --config configs/colmap.yaml data.root=<capture> ...``.
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pycolmap  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from neural_runs import save, summary, view_grid  # noqa: E402

from nsplat.data.synthetic_capture import CaptureSpec, ensure_capture  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
IMAGES = REPO / "docs" / "images" / "neural"
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
        dR = e[n].cam_from_world().rotation.matrix() @ sim.rotation.matrix().T @ g[n].cam_from_world().rotation.matrix().T
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
#: Overrides of ``configs/colmap.yaml`` per run. ``gt-hull`` has no SfM points to place its background
#: sphere by, so it gets the true environment sphere: ground truth throughout.
#: The recipe of ``configs/colmap.yaml`` before the gap study (ht estimator, no low-pass, surfels the
#: full 3-NN spacing, SfM points alone): every run but the last of ``GAP`` measures against it.
BEFORE = ["render.estimator=ht", "render.lowpass=1.0", "geometry.scale_factor=1.0", "geometry.sfm.fill=0"]
VARIANTS: dict[str, list[str]] = {
    "sfm": [*BEFORE],
    "gt-hull": [*BEFORE, "data.capture.sparse=sparse_gt/0", "data.capture.masks=masks", "geometry.init=hull",
                "geometry.grid=96", *GT_ENVIRONMENT],
    "bg-sphere-stage1": [*BEFORE, "neural.steps=0"],
    "bg-sphere-all-points-stage1": [*BEFORE, "neural.steps=0", "geometry.sfm.background_points=true"],
    "bg-none-stage1": [*BEFORE, "neural.steps=0", "geometry.background.model=none"],
}
#: Closing the gap to ``gt-hull`` (stage 1 alone, chosen on val): short screens at 8 epochs, each against
#: the same 8-epoch baseline, then the winner at the shipped 20 epochs (= the shipped configs/colmap.yaml).
S8 = [*BEFORE, "neural.steps=0", "geometry.optim.epochs=8"]
DENSIFY = ["geometry.optim.densify.enabled=true", "geometry.optim.densify.stop=6"]
FILL = ["geometry.sfm.fill=3000", "geometry.sfm.fill_box=bbox"]
LEVERS = ["render.estimator=sampled", "geometry.scale_factor=0.5", "render.lowpass=0.3"]
GAP: dict[str, list[str]] = {
    "s8-base": S8,
    "s8-densify": [*S8, *DENSIFY],
    "s8-fill-bbox": [*S8, *FILL, "geometry.sfm.fill_opacity=0.9"],
    "s8-levers": [*S8, *LEVERS],
    "s8-fill-bbox-faint": [*S8, *FILL, "geometry.sfm.fill_opacity=0.1"],
    "s8-fill-bbox-faint-levers": [*S8, *FILL, "geometry.sfm.fill_opacity=0.1", *LEVERS],
    "e20-fill-bbox-faint-levers": [*BEFORE, "neural.steps=0", *FILL, "geometry.sfm.fill_opacity=0.1", *LEVERS],
    "e20-gt-hull-levers": [*VARIANTS["gt-hull"], "neural.steps=0", *LEVERS],   # the reference, like for like
}
VARIANTS.update(GAP)
#: The two-stage comparison again with the shipped recipe (fill + levers for SfM; the levers for the hull).
VARIANTS.update({"sfm-shipped": [],
                 "gt-hull-levers": [*VARIANTS["gt-hull"], *LEVERS]})


def train(capture: Path, run: Path, overrides: list[str]) -> float:
    """One training run (skipped when it already evaluated); returns its wall time in seconds."""
    done = run / "eval_test" / "metrics.json" if "neural.steps=0" not in overrides else run / "eval_geometry.json"
    if done.is_file():
        return float("nan")
    cmd = [sys.executable, "train.py", "--config", "configs/colmap.yaml", "--run", str(run), "--overwrite",
           f"data.root={capture}", "data.capture.downscale=4", "log.progress=false", *overrides]
    print("+", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    run.mkdir(parents=True, exist_ok=True)
    with open(run.parent / f"{run.name}.log", "w") as log:
        subprocess.run(cmd, cwd=REPO, check=True, stdout=log, stderr=subprocess.STDOUT)
    (run / "train.log").write_text((run.parent / f"{run.name}.log").read_text())
    return time.perf_counter() - t0


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
    rows = {name: summary(name, args.runs / name, "test") for name in ("sfm", "gt-hull", "sfm-shipped", "gt-hull-levers")}
    stage1 = {name: json.loads((args.runs / name / "eval_geometry.json").read_text())
              for name in ("bg-sphere-stage1", "bg-sphere-all-points-stage1", "bg-none-stage1")}
    lines = ["| run | points | stage 1 alone val / test PSNR | val PSNR (last) | test PSNR | test SSIM | train s |",
             "|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        g, m = r["geometry"], r["test"]
        lines.append(f"| {name} | {m['points']} | {g['val']['psnr']['mean']:.2f} / {g['test']['psnr']['mean']:.2f} | "
                     f"{r['history'][-1]['val_psnr']:.2f} | {m['psnr']['mean']:.2f} ± {m['psnr']['std']:.2f} | "
                     f"{m['ssim']['mean']:.4f} | {r['timing']['train_total_s']:.0f} |")
    for name, g in stage1.items():
        lines.append(f"| {name} | {g['points']} | {g['val']['psnr']['mean']:.2f} / {g['test']['psnr']['mean']:.2f} "
                     f"| – | – | – | – |")
    gap_rows = {name: {**json.loads((args.runs / name / "eval_geometry.json").read_text()),
                       "stage1_s": json.loads((args.runs / name / "timing.json").read_text())["geometry_s"]}
                for name in GAP}
    lines += ["", "| stage 1 alone (closing the gap) | points | val PSNR | test PSNR | stage-1 s |", "|---|---|---|---|---|"]
    for name, g in gap_rows.items():
        lines.append(f"| {name} | {g['points']} | {g['val']['psnr']['mean']:.2f} | {g['test']['psnr']['mean']:.2f} | "
                     f"{g['stage1_s']:.0f} |")
    text = "\n".join(lines)
    gap = rows["gt-hull"]["test"]["psnr"]["mean"] - rows["sfm"]["test"]["psnr"]["mean"]
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / "own_capture.json"
    out.write_text(json.dumps({"command": "python benchmarks/own_capture.py " + " ".join(sys.argv[1:]),
                               "capture": str(capture), "spec": json.loads((capture / "spec.json").read_text()),
                               "sfm": sfm, "variants": VARIANTS, "walls_s": walls,
                               "test_psnr_gap_gt_minus_sfm_db": gap, "stage1_background": stage1,
                               "stage1_gap": gap_rows,
                               "runs": {k: {kk: vv for kk, vv in r.items() if kk != "per_view"} for k, r in rows.items()},
                               "markdown": text}, indent=1))
    fig = plt.figure(figsize=(13, 12))
    sub = fig.subfigures(2, 1)
    for panel, name in zip(sub, ("sfm", "gt-hull")):
        view_grid(panel, Path(rows[name]["run"]), rows[name]["per_view"][:4], "test", rows=3)
        panel.suptitle(f"{name}: test {rows[name]['test']['psnr']['mean']:.2f} dB", fontsize=10)
    save(fig, IMAGES / "own_capture.png", f"Own capture (pycolmap SfM {sfm['total_s']:.0f} s): SfM vs ground truth")
    print(text)
    print(f"SfM: {sfm}\ntest PSNR gap (gt-hull − sfm): {gap:.2f} dB\nwrote {out} and {IMAGES / 'own_capture.png'}")


if __name__ == "__main__":
    main()

"""Where the Chamfer gap between the gradient estimators comes from: accuracy or completeness, on or off the surface.

Reads the final point clouds (``reconstruction.ply``) of an estimator sweep (:mod:`benchmarks.estimator_sweep`;
its run folders under ``runs/bench/sweep-<setting>[-<tag>]/``) and splits each run's Chamfer distance into its
two directions, in units of the ground truth's bounding-box diagonal D:

* accuracy, reconstruction → ground truth: mean, median, 90th/99th percentile, and the share of the
  reconstructed points more than ``--far`` D from the ground-truth surface, split into inside / outside by the
  sign along the nearest ground-truth point's normal;
* completeness, ground truth → reconstruction: mean;
* how concentrated the accuracy error is: the share of the accuracy sum carried by the worst 5 % of points;
* what the points outside the surface look like: the median albedo (mean of the feature channels) and the
  median tangent std-dev (mean of the two, units of D) of the points on the surface (within ``--far``) and of
  those off it on the outside; with ``--contributions`` also their median visual contribution
  (:func:`nsplat.fitting.reposition.point_contributions`, Σ over the run's training views of w·‖colour‖, the measure
  repositioning uses), from the run's final checkpoint.

    python -m benchmarks.estimator_strays --setting cpu-long --shapes bunny teapot yoga1 yoga6
    python -m benchmarks.estimator_strays --setting cpu-long --tag long128 --shapes bunny --lrs 0.01

Writes ``benchmarks/results/estimator_strays-<setting>[-<tag>].json`` and prints a Markdown table. Runs whose
folder is missing are skipped (the sweep's JSON keeps their metrics, not their points).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from plyfile import PlyData
from scipy.spatial import cKDTree

from benchmarks.common import REPO, write_result
from benchmarks.estimator_sweep import load_run
from nsplat.data.pointclouds import load_dss_shape
from nsplat.fitting.reposition import point_contributions

ESTIMATORS = ("ht", "ht-pips", "paper", "sampled")


def split_distances(points: np.ndarray, gt: np.ndarray, normals: np.ndarray, far: float,
                    albedo: np.ndarray, scale: np.ndarray, contrib: np.ndarray) -> dict[str, float]:
    """Both Chamfer directions of ``points [N,3]`` against ``gt [M,3]`` (with unit ``normals [M,3]``), in units
    of the ground truth's bounding-box diagonal; medians of ``albedo [N]`` and ``scale [N]`` (world units) on
    the surface and outside it, and of ``contrib [N]`` (``None`` when it holds NaNs: not measured)."""
    diag = float(np.linalg.norm(gt.max(0) - gt.min(0)))
    d_pg, nearest = cKDTree(gt).query(points)
    d_pg = d_pg / diag
    d_gp = cKDTree(points).query(gt)[0] / diag
    side = np.einsum("ij,ij->i", points - gt[nearest], normals[nearest])
    off = d_pg > far
    worst = np.sort(d_pg)[::-1][:max(1, d_pg.size // 20)]
    on, out = ~off, off & (side >= 0)

    def median(a: np.ndarray, rows: np.ndarray) -> float | None:
        return float(np.median(a[rows])) if rows.any() and not np.isnan(a).any() else None
    return {"points": int(points.shape[0]), "accuracy_mean": float(d_pg.mean()),
            "accuracy_median": float(np.median(d_pg)), "accuracy_p90": float(np.percentile(d_pg, 90)),
            "accuracy_p99": float(np.percentile(d_pg, 99)), "off_inside": float(np.mean(off & (side < 0))),
            "off_outside": float(np.mean(off & (side >= 0))), "worst5_share": float(worst.sum() / d_pg.sum()),
            "completeness_mean": float(d_gp.mean()),
            "albedo_on": median(albedo, on), "albedo_outside": median(albedo, out),
            "scale_on": median(scale / diag, on), "scale_outside": median(scale / diag, out),
            "contribution_on": median(contrib, on), "contribution_outside": median(contrib, out),
            "chamfer": float(0.5 * (d_pg.mean() + d_gp.mean()))}


def contributions(run_dir: Path) -> np.ndarray:
    """``[N]`` visual contribution of every point of the run's final scene over its training views."""
    cfg, views, scene = load_run(run_dir)
    return point_contributions(scene, views.viewmats, views.Ks, cfg.data.width, cfg.data.height, cfg.render,
                               seed=cfg.seed).numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--setting", default="cpu-long")
    ap.add_argument("--tag", default="")
    ap.add_argument("--shapes", nargs="+", default=["bunny", "teapot", "yoga1", "yoga6"])
    ap.add_argument("--estimators", nargs="+", default=list(ESTIMATORS))
    ap.add_argument("--lrs", nargs="+", default=["0.01", "0.03", "0.1"])
    ap.add_argument("--far", type=float, default=0.05, help="'off the surface': farther than this (units of D)")
    ap.add_argument("--contributions", action="store_true",
                    help="also the median visual contribution on / outside (renders every training view)")
    ap.add_argument("--runs", default=str(REPO / "runs" / "bench"), help="folder of the sweeps' run folders")
    args = ap.parse_args()
    table = f"sweep-{args.setting}" + (f"-{args.tag}" if args.tag else "")
    rows = {}
    for shape in args.shapes:
        pc = load_dss_shape(shape)
        gt, normals = pc.points.double().numpy(), pc.normals.double().numpy()
        for est in args.estimators:
            for lr in args.lrs:
                ply = Path(args.runs) / table / f"{shape}-{est}-lr{float(lr):g}" / "reconstruction.ply"
                if not ply.is_file():
                    continue
                v = PlyData.read(str(ply))["vertex"]
                pts = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
                names = v.data.dtype.names
                albedo = np.stack([v[n] for n in names if n.startswith("f_")], 1).mean(1)
                scale = (np.exp(np.stack([v["scale_0"], v["scale_1"]], 1)).mean(1) if "scale_0" in names  # log std-devs
                         else np.full(pts.shape[0], np.nan))  # a scene without learnable scales
                contrib = contributions(ply.parent) if args.contributions else np.full(pts.shape[0], np.nan)
                rows[f"{shape}-{est}-lr{float(lr):g}"] = dict(
                    shape=shape, estimator=est, lr=float(lr),
                    **split_distances(pts, gt, normals, args.far, albedo, scale, contrib))
    head = (f"| shape | estimator | lr | accuracy mean / median / p90 / p99 | off the surface (> {args.far:g} D): "
            "inside / outside | worst 5 % share | completeness mean | median albedo: on / outside | "
            "median std-dev (D): on / outside | median contribution: on / outside | Chamfer |")
    lines = [head, "|---|---|---|---|---|---|---|---|---|---|---|"]

    def pair(a: float | None, b: float | None) -> str:
        return " / ".join("–" if x is None else f"{x:.3f}" for x in (a, b))

    for r in rows.values():
        lines.append(f"| {r['shape']} | {r['estimator']} | {r['lr']:g} | {r['accuracy_mean']:.4f} / "
                     f"{r['accuracy_median']:.4f} / {r['accuracy_p90']:.4f} / {r['accuracy_p99']:.4f} | "
                     f"{100 * r['off_inside']:.1f} % / {100 * r['off_outside']:.1f} % | {100 * r['worst5_share']:.0f} % | "
                     f"{r['completeness_mean']:.4f} | {pair(r['albedo_on'], r['albedo_outside'])} | "
                     f"{pair(r['scale_on'], r['scale_outside'])} | "
                     f"{pair(r['contribution_on'], r['contribution_outside'])} | {r['chamfer']:.4f} |")
    text = "\n".join(lines)
    write_result(f"estimator_strays-{args.setting}{'-' + args.tag if args.tag else ''}",
                 {"command": "python -m benchmarks.estimator_strays " + " ".join(sys.argv[1:]), "far": args.far,
                  "runs": rows, "markdown": text}, text)


if __name__ == "__main__":
    main()

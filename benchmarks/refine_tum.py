"""Room-scale refinement of a real RGB-D capture: ``configs/refine_tum.yaml`` on TUM RGB-D ``freiburg1_rpy`` (50
frames, a real drifting dense-visual-odometry trajectory and the motion-capture ground truth), before/after.

Runs the config in its own process (so its wall time, CPU time and peak memory are its own, end to end: reading
and fusing the frames, the refinement, fitting and scoring the held-out frames, the outputs), reads the run's
``metrics.json`` and writes ``benchmarks/results/refine_tum-fr1_rpy_50.json`` (320×240;
``refine_tum-fr1_rpy_50-640.json`` with ``--resolution 640``) with the figures the issue names, the CPU and the
run's before/after sheets under ``docs/images/refine_tum/``. The held-out frames are scored by the fair protocol
on both sides (``heldout.fit_before: true``, recorded as ``fit_before``): each gets the same per-frame camera +
exposure fit against the initial and the refined scene; the unfitted start is kept as ``psnr_before_unfitted`` /
``ssim_before_unfitted``.

``--ablation`` adds an ``ablation`` list: the shipped config (``all``) and three runs that learn less, each built
as overrides of it (:data:`ABLATION`): exposure only; exposure + poses; exposure + poses + scene (points, albedo,
SH) — the three without the outlier filter, a scene edit — each with held-out and training PSNR/SSIM and ATE/RPE.
Cameras that are not learned are frozen with ``poses.frozen`` (every training frame), so the held-out fit, which
needs pose corrections, is the same in every row.

    OMP_NUM_THREADS=2 python -m benchmarks.refine_tum                     # 320×240 (the fast setting)
    OMP_NUM_THREADS=2 python -m benchmarks.refine_tum --resolution 640    # 640×480 (configs/refine_tum_640.yaml)
    python -m benchmarks.refine_tum --set depth_loss=0 --name refine_tum-photometric   # an ablation
    OMP_NUM_THREADS=2 python -m benchmarks.refine_tum --ablation          # + the ablation (4 runs)
    python -m benchmarks.refine_tum --smoke                               # 10 frames at 160×120, 2 steps (CI)

The data: ``$NSPLAT_DATA/rgbd/tum_fr1_rpy_50`` or ``../shared/data/rgbd/tum_fr1_rpy_50``; when missing the script
says so in one line and exits 2.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

from benchmarks.common import IMAGES, REPO, RESULTS, markdown, run_config, write_result
from nsplat.data.paths import data_root
from nsplat.tasks.refine.data import DEFAULT_RGBD

CONFIGS = {320: "refine_tum.yaml", 640: "refine_tum_640.yaml"}
#: The run's sheets copied to docs/images/refine_tum/ (the 320×240 run's: the 640×480 ones look alike at 4× the size).
SHEETS = ("heldout_before.png", "heldout_after.png")
#: The smallest run (CI's smoke runs; not a result).
SMOKE = ["optim.steps=2", "heldout.steps=1", "data.rgbd.limit=10", "data.rgbd.downscale=4",
         "data.rgbd.fusion.max_points=5000", "data.rgbd.holdout_every=5"]
#: The ablation's rows other than ``all`` (the shipped config): name → overrides of it. ``{frozen}`` becomes
#: every training camera (poses not learned, the held-out fit unchanged).
ABLATION = {
    "exposure": ["scene.learn=[]", "shading.learn_sh=false", "poses.frozen={frozen}", "filter.enabled=false"],
    "exposure+poses": ["scene.learn=[]", "shading.learn_sh=false", "filter.enabled=false"],
    "exposure+poses+scene": ["filter.enabled=false"],
}
#: The figures an ablation row records (of the run's "after").
ROW = ("psnr", "ssim")


def _data() -> Path | None:
    """The data root that holds the sequence (``$NSPLAT_DATA``, else ``../shared/data``), or ``None``."""
    for root in (data_root(), REPO.parent / "shared" / "data"):
        if (root / DEFAULT_RGBD / "rgb.txt").is_file():
            return root
    return None


def summary(m: dict) -> dict:
    """The figures of a run's ``metrics.json`` that the record names at its top level."""
    b, a = m["before"], m["after"]
    out = {"heldout": {f"{k}_{when}": (b if when == "before" else a)["heldout"][k]
                       for k in ("psnr", "ssim", "lpips") for when in ("before", "after")},
           "train": {f"{k}_{when}": (b if when == "before" else a)["train"][k]
                     for k in ("psnr", "ssim", "lpips") for when in ("before", "after")}}
    for k in ("ate_rmse", "rpe_trans_rmse", "rpe_rot_rmse_deg", "points"):
        out[f"{k}_before"], out[f"{k}_after"] = b.get(k), a.get(k)
    for k in ("psnr", "ssim"):
        out["heldout"][f"{k}_before_unfitted"] = (b.get("heldout_unfitted") or b["heldout"])[k]
    out["heldout"]["ssim_gain_pct"] = 100.0 * (a["heldout"]["ssim"] / b["heldout"]["ssim"] - 1.0)
    out["heldout"]["psnr_gain_db"] = a["heldout"]["psnr"] - b["heldout"]["psnr"]
    out["ate_reduction_pct"] = 100.0 * (1.0 - a["ate_rmse"] / b["ate_rmse"])
    return out


def ablation_row(name: str, overrides: list[str], m: dict, wall_s: float) -> dict:
    """One row of the ablation from a run's ``metrics.json`` ``m``: its "after" held-out and training PSNR/SSIM,
    ATE and RPE."""
    a = m["after"]
    return {"name": name, "overrides": overrides, "wall_s": wall_s,
            **{f"heldout_{k}": a["heldout"][k] for k in ROW}, **{f"train_{k}": a["train"][k] for k in ROW},
            **{k: a.get(k) for k in ("ate_rmse", "rpe_trans_rmse", "rpe_rot_rmse_deg")}}


def ablation(config: str, name: str, overrides: list[str], m_all: dict, cost_all: dict, runs: Path,
             env: dict[str, str]) -> tuple[list[dict], str]:
    """The ablation rows (the shipped config's run ``m_all`` last, as ``all``) and their Markdown table."""
    frozen = "[" + ",".join(str(i) for i in range(m_all["frames"]["train"])) + "]"
    rows = []
    for row, extra in ABLATION.items():
        over = [*overrides, *(o.format(frozen=frozen) for o in extra)]
        run_dir = runs / f"bench-{name}-ablation-{row}"
        cost = run_config(config, run_dir, over, env=env)
        rows.append(ablation_row(row, [o.format(frozen="<every training frame>") for o in extra],
                                 json.loads((run_dir / "metrics.json").read_text()), cost["wall_s"]))
    rows.append(ablation_row("all", [], m_all, cost_all["wall_s"]))
    b = m_all["before"]
    start = ["start (fitted)", f"{b['heldout']['psnr']:.2f}", f"{b['heldout']['ssim']:.4f}",
             f"{b['train']['psnr']:.2f}", f"{b['train']['ssim']:.4f}", f"{100 * b['ate_rmse']:.2f}",
             f"{1000 * b['rpe_trans_rmse']:.2f}", f"{b['rpe_rot_rmse_deg']:.3f}"]
    table = markdown(["learned", "held-out PSNR", "held-out SSIM", "train PSNR", "train SSIM", "ATE (cm)",
                      "RPE (mm)", "RPE (deg)"],
                     [start] + [[r["name"], f"{r['heldout_psnr']:.2f}", f"{r['heldout_ssim']:.4f}",
                                 f"{r['train_psnr']:.2f}", f"{r['train_ssim']:.4f}", f"{100 * r['ate_rmse']:.2f}",
                                 f"{1000 * r['rpe_trans_rmse']:.2f}", f"{r['rpe_rot_rmse_deg']:.3f}"] for r in rows])
    return rows, table


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--resolution", type=int, choices=sorted(CONFIGS), default=320)
    ap.add_argument("--sequence", default=Path(DEFAULT_RGBD).name,
                    help="a TUM folder under <data root>/rgbd (tum_fr1_rpy_10hz: frames only, the trajectory tracked)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="further config overrides")
    ap.add_argument("--name", default=None, help="result name (default refine_tum-fr1_rpy_50[-640])")
    ap.add_argument("--smoke", action="store_true", help="the smallest run (CI; not a result)")
    ap.add_argument("--ablation", action="store_true",
                    help="also run the ablation (exposure; + poses; + scene; all) into the record's 'ablation'")
    args = ap.parse_args(argv)
    root = _data()
    if root is None:
        print(f"no TUM sequence at {data_root() / DEFAULT_RGBD} (set NSPLAT_DATA to the folder holding "
              f"{DEFAULT_RGBD})", file=sys.stderr)
        return 2
    name = args.name or f"refine_{args.sequence}".replace("refine_tum_", "refine_tum-") + \
        ("" if args.resolution == 320 else "-640")
    seq_over = [] if args.sequence == Path(DEFAULT_RGBD).name else [f"data.rgbd.root={root / 'rgbd' / args.sequence}"]
    overrides = [*seq_over, *(SMOKE if args.smoke else []), *args.set]
    runs = RESULTS.parent / "runs" if os.environ.get("NSPLAT_BENCH_OUT") else REPO / "runs"
    run_dir = runs / f"bench-{name}"
    env = {"NSPLAT_DATA": str(root)}
    cost = run_config(CONFIGS[args.resolution], run_dir, overrides, env=env)
    m = json.loads((run_dir / "metrics.json").read_text())
    s = summary(m)
    record = {**s, "fit_before": "heldout_unfitted" in m["before"], "resolution": m["resolution"],
              "frames": m["frames"], "config": CONFIGS[args.resolution],
              "overrides": overrides, "wall_s": cost["wall_s"], "cpu_s": cost["cpu_s"],
              "peak_rss_gb": m["peak_rss_gb"], "steps": m["steps"], "steps_wall_s": m["steps_wall_s"],
              "steps_cpu_s": m["steps_cpu_s"], "removed": m["removed"], "load": [cost["load_before"],
                                                                                 cost["load_after"]],
              "threads": os.environ.get("OMP_NUM_THREADS"), "sequence": args.sequence,
              "trajectory": m["before"].get("source"), "before": m["before"], "after": m["after"]}
    record["ate_rmse_start"] = (m["before"].get("start") or {}).get("ate_rmse")  # the re-tracked start
    if (m["before"].get("source") or {}).get("trajectory") == "estimate":
        record["ate_rmse_estimate"] = m["before"].get("ate_rmse")
        record["tracker"] = m["before"]["source"].get("tracker")
    out = IMAGES / "refine_tum"
    out.mkdir(parents=True, exist_ok=True)
    for sheet in SHEETS if args.resolution == 320 else ():
        src = run_dir / "before_after" / sheet
        if src.is_file():
            shutil.copyfile(src, out / f"{name}-{sheet}")
    h = s["heldout"]
    rows = [["held-out PSNR (dB)", f"{h['psnr_before']:.2f}", f"{h['psnr_after']:.2f}", f"{h['psnr_gain_db']:+.2f} dB"],
            ["held-out SSIM", f"{h['ssim_before']:.4f}", f"{h['ssim_after']:.4f}", f"{h['ssim_gain_pct']:+.1f} %"],
            ["train PSNR (dB)", f"{s['train']['psnr_before']:.2f}", f"{s['train']['psnr_after']:.2f}", ""],
            ["train SSIM", f"{s['train']['ssim_before']:.4f}", f"{s['train']['ssim_after']:.4f}", ""],
            ["ATE RMSE (cm)", f"{100 * s['ate_rmse_before']:.2f}", f"{100 * s['ate_rmse_after']:.2f}",
             f"{-s['ate_reduction_pct']:+.1f} %"],
            ["RPE trans. RMSE (mm)", f"{1000 * s['rpe_trans_rmse_before']:.2f}",
             f"{1000 * s['rpe_trans_rmse_after']:.2f}", ""],
            ["RPE rot. RMSE (deg)", f"{s['rpe_rot_rmse_deg_before']:.3f}", f"{s['rpe_rot_rmse_deg_after']:.3f}", ""]]
    table = markdown(["", "before (SLAM start, fitted)" if record["fit_before"] else "before (SLAM start)", "after",
                      "change"], rows)
    table += (f"\n\n{m['resolution'][0]}×{m['resolution'][1]}, {m['steps']} steps: {cost['wall_s'] / 60:.1f} min wall, "
              f"{cost['cpu_s'] / 60:.1f} min CPU, peak RSS {m['peak_rss_gb']:.2f} GB")
    if args.ablation:
        record["ablation"], ab_table = ablation(CONFIGS[args.resolution], name, overrides, m, cost, runs, env)
        table += "\n\nablation (held-out frames fitted on every row):\n\n" + ab_table
    write_result(name, record, table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

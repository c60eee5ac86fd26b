"""How far off a trajectory the refinement brings back: the shared TUM sequences' ground truth with a seeded smooth
drift added (:func:`nsplat.tasks.refine.trajectory.inject_drift`: errors that accumulate along the sequence as
odometry's do, sized so the start's ATE RMSE after the SE(3) alignment is 2, 5, 10 and 20 cm), refined with the
shipped ``configs/refine_tum.yaml`` as a user runs it (only ``data.rgbd.root`` and ``data.rgbd.trajectory``
set; each run in its own process).

The drifted trajectory is written as a TUM file at the frames' RGB timestamps (the ground truth associated to
them as the refine task associates it). Each row records the start's ATE (``ate_rmse_before``), the re-tracked
start's (``ate_rmse_start``, when the config re-tracks) and the refined trajectory's (``ate_rmse_after``), with
RPE, the held-out figures and the run's wall / CPU time. The ground truth builds the start and scores; it
chooses nothing.

Writes ``benchmarks/results/refine_drift.json`` and prints a Markdown table (and the largest drift all of whose
seeds come back to ``--target`` or better).

    OMP_NUM_THREADS=2 python -m benchmarks.refine_drift                                  # rpy_50, 3 seeds
    python -m benchmarks.refine_drift --drifts 0.1 --seeds 0 --set optim.steps=40        # one quick row
    python -m benchmarks.refine_drift --smoke                                            # tiny (CI; not a result)
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

from benchmarks.common import REPO, RESULTS, markdown, run_config, write_result
from nsplat.data.paths import data_root
from nsplat.data.rgbd import tum_files
from nsplat.data.tum_format import write_trajectory
from nsplat.tasks.refine.trajectory import inject_drift

#: The smallest run (CI's smoke runs; not a result).
SMOKE = ["data.rgbd.limit=10", "data.rgbd.downscale=4", "optim.steps=2", "heldout.steps=1",
         "data.rgbd.tracking.rounds=0", "log.checkpoint=0", "log.images=0"]


def _root() -> Path:
    for root in (data_root(), REPO.parent / "shared" / "data"):
        if (root / "rgbd").is_dir():
            return root
    return data_root()


def drifted_file(seq_dir: Path, seed: int, drift_m: float, out: Path) -> Path:
    """The ground truth of ``seq_dir``'s frames with drift injected, as a TUM trajectory file ``out``."""
    files = tum_files(seq_dir, "", "groundtruth.txt", 0.02)
    return write_trajectory(out, files.timestamps, inject_drift(files.c2w_gt, seed, drift_m),
                            comment=f"ground truth with drift (seed {seed}, ATE {drift_m} m)")


def row(seq: str, seed: int, drift_m: float, run: Path, cost: dict[str, Any]) -> dict[str, Any]:
    m = json.loads((run / "metrics.json").read_text())
    b, a = m["before"], m["after"]
    return {"sequence": seq, "seed": seed, "drift_m": drift_m, "ate_rmse_before": b["ate_rmse"],
            "ate_rmse_start": (b.get("start") or {}).get("ate_rmse"), "ate_rmse_after": a["ate_rmse"],
            "rpe_trans_before": b["rpe_trans_rmse"], "rpe_trans_after": a["rpe_trans_rmse"],
            "rpe_rot_deg_before": b["rpe_rot_rmse_deg"], "rpe_rot_deg_after": a["rpe_rot_rmse_deg"],
            "heldout_ssim_before": b["heldout"]["ssim"], "heldout_ssim_after": a["heldout"]["ssim"],
            "wall_s": cost["wall_s"], "cpu_s": cost["cpu_s"], "peak_rss_gb": m.get("peak_rss_gb")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sequences", nargs="+", default=["tum_fr1_rpy_50"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--drifts", nargs="+", type=float, default=[0.02, 0.05, 0.10, 0.20])
    ap.add_argument("--target", type=float, default=0.025, help="ATE RMSE (m) a start must come back to")
    ap.add_argument("--set", nargs="*", default=[], help="config overrides (not the shipped recipe: say so)")
    ap.add_argument("--smoke", action="store_true", help="the smallest run (CI; not a result)")
    ap.add_argument("--out", default="refine_drift")
    args = ap.parse_args()
    root = _root()
    missing = [s for s in args.sequences if not (root / "rgbd" / s).is_dir()]
    if missing:
        print(f"no TUM sequence at {root / 'rgbd' / missing[0]} (set NSPLAT_DATA to the folder holding rgbd/)",
              file=sys.stderr)
        return 2
    overrides = [*(SMOKE if args.smoke else []), *args.set]
    if args.smoke:
        args.seeds, args.drifts = args.seeds[:1], args.drifts[:1]
    rows = []
    with tempfile.TemporaryDirectory(prefix="nsplat-drift-") as tmp:
        for seq in args.sequences:
            for drift in args.drifts:
                for seed in args.seeds:
                    tag = f"{seq}-seed{seed}-{round(1000 * drift)}mm"  # no dot: run_config's log is RUN.log
                    traj = drifted_file(root / "rgbd" / seq, seed, drift, Path(tmp) / f"{tag}.txt")
                    run = Path(tmp) / f"run-{tag}"
                    (RESULTS.parent / "runs").mkdir(parents=True, exist_ok=True)
                    cost = run_config("refine_tum.yaml", run, [f"data.rgbd.root={root / 'rgbd' / seq}",
                                                               f"data.rgbd.trajectory={traj}", *overrides],
                                      env={"NSPLAT_DATA": str(root), "OMP_NUM_THREADS":
                                           os.environ.get("OMP_NUM_THREADS", "2")},
                                      log=RESULTS.parent / "runs" / f"refine_drift-{tag}.log")
                    rows.append(row(seq, seed, drift, run, cost))
                    r = rows[-1]
                    print(f"{seq} seed {seed} drift {drift}: ATE {r['ate_rmse_before']:.4f} -> "
                          f"{r['ate_rmse_after']:.4f} m ({r['wall_s']:.0f} s)", flush=True)
                    report(rows, args, overrides, final=False)
    report(rows, args, overrides, final=True)
    return 0


def report(rows: list[dict[str, Any]], args: argparse.Namespace, overrides: list[str], final: bool) -> None:
    """Write the record (after every row, so a long run keeps what it measured) and, when ``final``, print the
    table and the largest drift that comes back."""
    back = [d for d in sorted({r["drift_m"] for r in rows})
            if all(r["ate_rmse_after"] <= args.target for r in rows if r["drift_m"] == d)]
    largest = max((d for d in back if all(b in back for b in {r["drift_m"] for r in rows} if b <= d)), default=None)
    table = markdown(
        ["sequence", "seed", "drift (cm)", "ATE before (cm)", "re-tracked (cm)", "ATE after (cm)",
         "RPE trans before → after (cm)", "held-out SSIM before → after", "wall (s)"],
        [[r["sequence"], r["seed"], f"{100 * r['drift_m']:.0f}", f"{100 * r['ate_rmse_before']:.2f}",
          "—" if r["ate_rmse_start"] is None else f"{100 * r['ate_rmse_start']:.2f}",
          f"{100 * r['ate_rmse_after']:.2f}", f"{100 * r['rpe_trans_before']:.2f} → {100 * r['rpe_trans_after']:.2f}",
          f"{r['heldout_ssim_before']:.3f} → {r['heldout_ssim_after']:.3f}", f"{r['wall_s']:.0f}"] for r in rows])
    write_result(args.out, {"rows": rows, "target_m": args.target, "largest_drift_back_m": largest,
                            "complete": final, "overrides": overrides, "config": "configs/refine_tum.yaml"},
                 table if final else None)
    if final:
        print(f"largest drift whose every seed comes back to <= {100 * args.target:.1f} cm: "
              f"{'none' if largest is None else f'{100 * largest:.0f} cm'}")


if __name__ == "__main__":
    raise SystemExit(main())

"""Real photos as your own capture: the 80 lego_400 photos through README's pycolmap snippet, then
``configs/colmap.yaml`` at 100².

The 80 photos of ``nerf_synthetic/lego_400`` (train, val and test, RGBA composited on white: a studio capture)
are written to ``<cache>/lego_capture/images`` under their split-prefixed names; SIFT features are extracted and
matched exhaustively once (README's snippet: one OPENCV camera, default options), and pycolmap's incremental
mapper then runs once per seed (it is not deterministic: each seed picks its own initial pair and world frame)
into ``<cache>/lego_capture/sfm-<seed>/sparse``. Each SfM output trains with
``python train.py --config configs/colmap.yaml data.root=<scene> data.capture.downscale=4`` (every 8th photo by
name held out as test, every 8th of the rest as val). ``--similarity`` also trains the first SfM output after a
random similarity transform of its world (rotation, translation by 5 scene units, scale 0.2–5): the training
frame must not depend on the world frame SfM picked.

    python -m benchmarks.lego_capture --seeds 0 1 2 --similarity     # SfM, then one training per SfM output
    python -m benchmarks.lego_capture --seeds 3 --sfm-only           # one more SfM run, no training
    python -m benchmarks.lego_capture --seeds 0 1 2 --similarity --report   # tabulate the finished runs only
    python -m benchmarks.lego_capture --seeds 1 --train-seed 1       # train seed 1's SfM output again, seed=1
    python -m benchmarks.lego_capture --seeds 2 --tag steps1000 --set neural.steps=1000   # a config variant

Merges its rows into ``benchmarks/results/lego_capture.json`` (per run: SfM registered images, points and time,
the training frame's diagnosis, stage-1 and final test PSNR, the val curves, wall and CPU seconds, any config
overrides, and ``measured``: the commit, date, load average and command the row was measured with); rows of
runs not made by this call are kept as they were, a row of the same name is replaced. Prints a Markdown table
of every row.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pycolmap
import torch
from scipy.spatial.transform import Rotation

from benchmarks.common import REPO, machine, markdown, read_result, run_config, write_result
from nsplat.data.colmap import load_colmap
from nsplat.data.views import PosedViews
from nsplat.tasks.neural.frame import capture_frame

LEGO = Path("/work/shared/data/nerf_synthetic/lego_400")


def photos(source: Path, scene: Path) -> int:
    """Write the RGBA photos of ``source``'s splits composited on white into ``scene/images``; returns the count."""
    out = scene / "images"
    if out.is_dir() and any(out.iterdir()):
        return len(list(out.iterdir()))
    tmp = scene / "images.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for split in ("train", "val", "test"):
        for f in sorted((source / split).glob("*.png")):
            rgba = iio.imread(f).astype(np.float32) / 255.0
            rgb = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])
            iio.imwrite(tmp / f"{split}_{f.name}", np.round(rgb * 255).astype(np.uint8))
    tmp.rename(out)
    return len(list(out.iterdir()))


def features(scene: Path, threads: int) -> dict[str, float]:
    """README's extraction and exhaustive matching into ``scene/db.db`` once; returns their seconds."""
    db = scene / "db.db"
    stamp = scene / "features.json"
    if stamp.is_file():
        return json.loads(stamp.read_text())
    db.unlink(missing_ok=True)
    t0 = time.perf_counter()
    pycolmap.extract_features(db, scene / "images", camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=pycolmap.ImageReaderOptions(camera_model="OPENCV"),
                              extraction_options=pycolmap.FeatureExtractionOptions(num_threads=threads),
                              device=pycolmap.Device.cpu)
    t1 = time.perf_counter()
    pycolmap.match_exhaustive(db, matching_options=pycolmap.FeatureMatchingOptions(num_threads=threads),
                              device=pycolmap.Device.cpu)
    out = {"extract_s": t1 - t0, "match_s": time.perf_counter() - t1}
    stamp.write_text(json.dumps(out))
    return out


def sfm(scene: Path, seed: int, threads: int) -> Path:
    """Incremental mapping with ``seed`` into ``scene/sfm-<seed>/sparse`` (``images`` linked beside it);
    returns the run's root (a COLMAP-layout folder). Its ``sfm.json`` has the models, sizes and seconds."""
    root = scene / f"sfm-{seed}"
    if (root / "sfm.json").is_file():
        return root
    (root / "sparse").mkdir(parents=True, exist_ok=True)
    if not (root / "images").exists():
        (root / "images").symlink_to(scene / "images", target_is_directory=True)
    options = pycolmap.IncrementalPipelineOptions(num_threads=threads, random_seed=seed)
    t0 = time.perf_counter()
    models = pycolmap.incremental_mapping(scene / "db.db", scene / "images", root / "sparse", options=options)
    info = {"seed": seed, "map_s": time.perf_counter() - t0,
            "models": {str(k): {"registered": r.num_reg_images(), "points": r.num_points3D(),
                                "mean_reprojection_error_px": r.compute_mean_reprojection_error()}
                       for k, r in models.items()}}
    (root / "sfm.json").write_text(json.dumps(info, indent=1))
    return root


def similar(root: Path, seed: int) -> Path:
    """A copy of ``root`` whose every SfM model is moved by a random similarity (``seed``)."""
    out = root.with_name(root.name + f"-sim{seed}")
    if (out / "sfm.json").is_file():
        return out
    (out / "sparse").mkdir(parents=True, exist_ok=True)
    if not (out / "images").exists():
        (out / "images").symlink_to(root / "images", target_is_directory=True)
    rng = np.random.default_rng(seed)
    sim = pycolmap.Sim3d(float(np.exp(rng.uniform(-np.log(5.0), np.log(5.0)))),
                         pycolmap.Rotation3d(Rotation.random(random_state=rng).as_matrix()), rng.uniform(-5.0, 5.0, 3))
    for model in sorted((root / "sparse").iterdir()):
        rec = pycolmap.Reconstruction(str(model))
        rec.transform(sim)
        (out / "sparse" / model.name).mkdir(exist_ok=True)
        rec.write_binary(str(out / "sparse" / model.name))
    info = json.loads((root / "sfm.json").read_text())
    info["similarity"] = sim.matrix().tolist()
    (out / "sfm.json").write_text(json.dumps(info, indent=1))
    return out


def train(root: Path, run: Path, seed: int = 0, overrides: list[str] = ()) -> dict:
    """``configs/colmap.yaml`` at 100² on ``root`` with training ``seed`` and config ``overrides`` (``key=value``);
    returns ``run_config``'s record and the exit status."""
    if (run / "eval_test" / "metrics.json").is_file():
        return {"skipped": True, "returncode": 0}
    try:
        return run_config(REPO / "configs" / "colmap.yaml", run,
                          [f"data.root={root}", "data.capture.downscale=4", "log.progress=false", f"seed={seed}",
                           *overrides])
    except RuntimeError as err:  # a run that stops with its message is a result too
        return {"returncode": 1, "error": str(err)}


def frame_of(root: Path) -> tuple[dict, torch.Tensor]:
    """The training frame ``configs/colmap.yaml`` finds for the SfM output at ``root`` (no training): its
    diagnosis, the registered images and the SfM points' median distance from the SfM world's origin (COLMAP
    centres its world on the cameras) in camera distances; and the cameras in it (``[V,4,4]``, by name)."""
    cap = load_colmap(root, downscale=4)
    every = PosedViews(images=torch.empty(len(cap.train) + len(cap.test), cap.train.height, cap.train.width, 0),
                       viewmats=torch.cat([cap.train.viewmats, cap.test.viewmats]),
                       Ks=torch.cat([cap.train.Ks, cap.test.Ks]), names=cap.train.names + cap.test.names)
    frame = capture_frame(every, cap.points, radius=3.2)
    out = frame.diagnosis()
    out["registered"] = len(every)
    out["points_from_sfm_origin_radii"] = float(cap.points.xyz.double().median(0).values.norm()) / frame.radius
    order = sorted(range(len(every)), key=lambda i: every.names[i])
    return out, frame.viewmats(every.viewmats)[order]


#: The commit (and whether the tree had changes) when this process started: the code it runs.
STARTED = {k: v for k, v in machine().items() if k in ("commit", "dirty")}


def stamp() -> dict:
    """When and at what a row was measured: the commit the process started at (:data:`STARTED`), the date
    and load average now, and the command line."""
    m = machine()
    return {**STARTED, "date": m["date"], "load_avg": m["load_avg"],
            "command": "python -m benchmarks.lego_capture " + " ".join(sys.argv[1:])}


def result(root: Path, run: Path, ran: dict) -> dict:
    """One row: SfM record, the frame diagnosis, stage-1 and final test PSNR and the stage-1 and stage-2 val curves
    (absent when the run stopped), the load before and after training and the :func:`stamp` it was measured at."""
    row = {"root": str(root), "run": str(run), "sfm": json.loads((root / "sfm.json").read_text()),
           "returncode": ran.get("returncode"), "wall_s": ran.get("wall_s"), "cpu_s": ran.get("cpu_s"),
           "load_before": ran.get("load_before"), "load_after": ran.get("load_after"), "measured": stamp()}
    for name, key in (("frame", "capture_frame.json"), ("test", "eval_test/metrics.json"),
                      ("stage1", "eval_geometry.json"), ("stage1_history", "geometry_history.json"),
                      ("stage2_history", "history.json")):
        if (run / key).is_file():
            row[name] = json.loads((run / key).read_text())
    if run.with_suffix(".log").is_file():
        row["log_tail"] = run.with_suffix(".log").read_text().splitlines()[-5:]
    return row


def table(rows: dict[str, dict], count: int) -> str:
    """The Markdown table of ``rows`` (name -> row of :func:`result`) of a capture of ``count`` photos."""
    return markdown(["run", "registered / photos", "SfM points", "exit", "stage 1 val / test PSNR", "end val PSNR",
                    "test PSNR", "train wall / CPU s", "measured at"],
                    [[k, f"{max(m['registered'] for m in r['sfm']['models'].values())} / {count}",
                     max(m["points"] for m in r["sfm"]["models"].values()), r["returncode"],
                     f"{r['stage1']['val']['psnr']['mean']:.2f} / {r['stage1']['test']['psnr']['mean']:.2f}"
                     if "stage1" in r else "-",
                     f"{r['stage2_history']['history'][-1]['val_psnr']:.2f}" if "stage2_history" in r else "-",
                     f"{r['test']['psnr']['mean']:.2f}" if "test" in r else "-",
                     f"{r['wall_s']:.0f} / {r['cpu_s']:.0f}" if r.get("cpu_s") else
                     f"{r['wall_s']:.0f} / -" if r.get("wall_s") else "-",
                     f"{r['measured']['commit'][:7]} {r['measured']['date'][:16]}"] for k, r in rows.items()])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--source", type=Path, default=LEGO)
    ap.add_argument("--cache", type=Path, default=REPO / "data_cache")
    ap.add_argument("--runs", type=Path, default=REPO / "runs" / "lego_capture")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--similarity", action="store_true", help="also train the first SfM run moved by a similarity")
    ap.add_argument("--train-seed", type=int, default=0,
                    help="training seed (`seed=`); runs with a seed other than 0 are named <SfM run>-train<seed>")
    ap.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="config overrides of a variant (select it on the val curve, not on test); needs --tag")
    ap.add_argument("--tag", default="", help="variant name: its runs are named <SfM run>-<tag>")
    ap.add_argument("--sfm-only", action="store_true")
    ap.add_argument("--report", action="store_true", help="train nothing: tabulate the finished runs")
    args = ap.parse_args()
    if args.set and not args.tag:
        ap.error("--set needs --tag: a variant's rows must not replace the default config's")
    scene = args.cache / "lego_capture"
    count = photos(args.source, scene)
    feats = features(scene, args.threads)
    roots = [sfm(scene, s, args.threads) for s in args.seeds]
    if args.similarity:  # trained second, beside the run it moves
        roots.insert(1, similar(roots[0], 1234))
    if args.sfm_only:
        return
    rows = {}
    for root in roots:
        name = (root.name + (f"-{args.tag}" if args.tag else "")
                + (f"-train{args.train_seed}" if args.train_seed else ""))
        run = args.runs / name
        if args.report:
            if (run / "capture_frame.json").is_file():
                done = (run / "finished.json").is_file()  # wall time from the run folder's first and last file
                wall = (run / "finished.json").stat().st_mtime - (run / "config.yaml").stat().st_mtime if done else None
                rows[name] = result(root, run, {"returncode": 0 if done else None, "wall_s": wall})
            continue
        rows[name] = result(root, run, train(root, run, args.train_seed, args.set))
        if args.set:
            rows[name]["overrides"] = args.set
    frames, cams = {}, {}
    for root in sorted(scene.glob("sfm-*")):
        if (root / "sfm.json").is_file():
            frames[root.name], cams[root.name] = frame_of(root)
            frames[root.name]["measured"] = stamp()
    for name in frames:  # a moved SfM world: its training-frame cameras against the original's
        if "-sim" in name and cams[name].shape == cams[name.split("-sim")[0]].shape:
            frames[name]["cameras_max_diff_vs_unmoved"] = float((cams[name] - cams[name.split("-sim")[0]]).abs().max())
    before = read_result("lego_capture") or {}
    rows, frames = {**before.get("runs", {}), **rows}, {**before.get("frames", {}), **frames}
    table_md = table(rows, count)
    write_result("lego_capture", {"photos": count, "features": feats, "runs": rows, "frames": frames,
                                  "markdown": table_md}, table_md)


if __name__ == "__main__":
    main()

"""A capture like instant-ngp's fox, made here: does ``configs/transforms.yaml`` train on it as it ships (issue 70)?

instant-ngp's demo ``data/nerf/fox`` is 50 phone photos in portrait with a ``transforms.json`` from colmap2nerf
that lists 67 frames (17 photos absent) and no point cloud. This builds the same situation from our own renders:

1. the procedural scene (6 objects, seed 3) photographed in front of a textured environment (the clutter: every
   pixel is covered, no masks) through a distorted ``OPENCV`` phone-like camera
   (:mod:`nsplat.data.synthetic_capture`), 67 views at 240², each cropped to its central 135 columns: portrait
   135×240 (the fox at ``downscale=8``);
2. poses from the photos alone, as colmap2nerf gets them: pycolmap SfM (:func:`~nsplat.data.synthetic_capture.run_sfm`,
   focal prior 5 % off), written as ``transforms.json`` (OpenGL camera-to-world, ``OPENCV`` fields at the top);
   the SfM model and its points are then deleted, and 17 of the photos (every fourth) too;
3. ``python train.py --config configs/transforms.yaml data.root=<folder> data.capture.downscale=1``: the frames
   present, the start from points triangulated from them, stage 2 kept at its best validation.

Written: ``benchmarks/results/fox_like.json`` (held-out PSNR/SSIM mean and worst view, SfM figures, start, time).

    python -m benchmarks.fox_like            # about 15 min on 2 cores
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pycolmap

from benchmarks.common import REPO, run_config, write_result
from nsplat.data.synthetic_capture import FOCAL_PRIOR_ERROR, CaptureSpec, render_capture, run_sfm

SPEC = CaptureSpec(seed=3, objects=6, resolution=240, views=67)
#: Portrait width after the crop, and the columns cut on the left.
WIDTH, LEFT = 135, 52
#: Every this-many-th photo is deleted after SfM (17 of 67): the frames colmap2nerf listed whose files are gone.
DROP_EVERY = 4


def crop_photos(folder: Path) -> None:
    """Crop every photo of ``folder/images`` to columns ``LEFT … LEFT + WIDTH`` (portrait 135×240)."""
    for path in sorted((folder / "images").iterdir()):
        iio.imwrite(path, iio.imread(path)[:, LEFT:LEFT + WIDTH])


def write_transforms(rec: pycolmap.Reconstruction, path: Path) -> int:
    """``transforms.json`` of ``rec``'s registered images as colmap2nerf writes it (one ``OPENCV`` camera at the top,
    OpenGL camera-to-world matrices); returns the frame count."""
    camera = next(iter(rec.cameras.values()))
    fx, fy, cx, cy, k1, k2, p1, p2 = camera.params
    frames = []
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        w2c = np.eye(4)
        w2c[:3] = image.cam_from_world().matrix()
        frames.append({"file_path": f"images/{image.name}", "transform_matrix": (np.linalg.inv(w2c) @ flip).tolist()})
    meta = {"camera_model": "OPENCV", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": camera.width,
            "h": camera.height, "k1": k1, "k2": k2, "p1": p1, "p2": p2, "aabb_scale": 16, "frames": frames}
    path.write_text(json.dumps(meta, indent=1))
    return len(frames)


def build(folder: Path) -> dict:
    """Photograph, crop, run SfM, write ``transforms.json``, then delete the model and :data:`DROP_EVERY`'s photos."""
    render_capture(SPEC, folder)
    crop_photos(folder)
    sfm = run_sfm(folder, SPEC.camera().focal_length_x * FOCAL_PRIOR_ERROR, threads=2)
    rec = pycolmap.Reconstruction(str(folder / "sparse" / "0"))
    listed = write_transforms(rec, folder / "transforms.json")
    for sub in ("sparse", "sparse_gt", "sfm", "masks"):
        shutil.rmtree(folder / sub, ignore_errors=True)
    (folder / "sfm.json").unlink(missing_ok=True)
    photos = sorted((folder / "images").iterdir())
    for path in photos[::DROP_EVERY]:
        path.unlink()
    return {"sfm": sfm, "listed_frames": listed, "photos": len(photos) - len(photos[::DROP_EVERY])}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, default=Path("runs/bench-fox_like"), help="where the capture and run go")
    ap.add_argument("--reuse", action="store_true", help="train on the capture an earlier run built")
    args = ap.parse_args(argv)
    folder = args.runs / "capture"
    if args.reuse and (folder / "made.json").is_file():
        made = json.loads((folder / "made.json").read_text())
    else:
        shutil.rmtree(folder, ignore_errors=True)
        args.runs.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".fox-like-", dir=args.runs))
        made = build(tmp)
        (tmp / "made.json").write_text(json.dumps(made, indent=1))
        shutil.move(str(tmp), folder)
    run = args.runs / "run"
    cost = run_config(REPO / "configs" / "transforms.yaml", run, [f"data.root={folder.resolve()}",
                                                                 "data.capture.downscale=1"])
    metrics = json.loads((run / "eval_test" / "metrics.json").read_text())
    views = json.loads((run / "eval_test" / "per_view.json").read_text())["views"]
    worst = min(views, key=lambda v: v["psnr"])
    log = Path(cost["log"]).read_text()
    record = {"capture": {**made, "spec": {"seed": SPEC.seed, "objects": SPEC.objects, "views": SPEC.views,
                                           "size": [WIDTH, SPEC.resolution]}},
              "test_psnr": metrics["psnr"], "test_ssim": metrics["ssim"], "views": len(views),
              "worst_view": {"name": worst["name"], "psnr": worst["psnr"], "ssim": worst.get("ssim")},
              "triangulated": "triangulat" in log, "skipped_warning": "skipped" in log or "not in the folder" in log,
              "wall_s": cost["wall_s"], "cpu_s": cost["cpu_s"], "load_avg": [cost["load_before"][0],
                                                                             cost["load_after"][0]]}
    table = (f"fox-like capture ({made['photos']} of {made['listed_frames']} listed photos, 135×240): held-out "
             f"{metrics['psnr']['mean']:.2f} ± {metrics['psnr']['std']:.2f} dB, SSIM {metrics['ssim']['mean']:.4f}, "
             f"worst view {worst['psnr']:.2f} dB; {cost['wall_s'] / 60:.1f} min")
    write_result("fox_like", record, table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

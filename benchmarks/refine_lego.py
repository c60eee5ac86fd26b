"""Pose refinement on NeRF-synthetic lego: rotation/translation error and PSNR/SSIM before/after.

Three stages, all on the CPU at low resolution:

0. **Cloud.** A visual hull carved from the masks (alpha) of all training views with the true poses
   (voxel kept when it projects inside the dilated mask of every view that sees it), reduced to its
   surface voxels; normals from the gradient of the blurred occupancy, colours the median of the
   pixels the voxel projects to, std-dev 0.6 voxel.
1. **Scene fit with the true poses** (task ``refine``, ``poses.learn=false``, plain albedo, white
   background): positions, normals, scales, opacity and albedo are fitted to the first ``--frames``
   training views. This is the "trained" scene.
2. **Pose refinement**: the same views, every pose perturbed by exactly 2° and 2 % of the cloud's
   largest extent (``data.nerf.rot_deg/trans_frac``), the fitted scene frozen; only the SE(3)
   corrections are learned (the fitted cloud fixes the world frame).

Writes ``benchmarks/results/refine_lego.json`` and before/after images to ``docs/images/refine/``.

    OMP_NUM_THREADS=2 python -m benchmarks.refine_lego [--resolution 64 --frames 24]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
import torch.nn.functional as F

from benchmarks.common import IMAGES as ALL_IMAGES
from benchmarks.common import REPO as ROOT
from benchmarks.common import run_config, write_result
from nsplat.data.nerf_synthetic import load_split
from nsplat.data.paths import data_root
from nsplat.scene import SceneConfig, SurfelScene

IMAGES = ALL_IMAGES / "refine"
LEGO = data_root() / "nerf_synthetic" / "lego_400"


def carve(grid: int, resolution: int, bound: float = 1.3) -> dict[str, torch.Tensor]:
    """Surface voxels of the visual hull of all training views (see the module docstring)."""
    v = load_split(LEGO, "train", resolution=resolution)
    H, W = v.height, v.width
    alpha = v.masks
    alpha = F.max_pool2d(alpha[:, None], 3, 1, 1)[:, 0]  # dilate 1 px: conservative hull
    s = (torch.arange(grid, dtype=torch.float64) + 0.5) / grid * 2 * bound - bound
    X, Y, Z = torch.meshgrid(s, s, s, indexing="ij")
    pts = torch.stack([X, Y, Z], -1).reshape(-1, 3)
    occ = torch.ones(pts.shape[0], dtype=torch.bool)
    colours = []
    for b in range(len(v)):
        V, K = v.viewmats[b].double(), v.Ks[b].double()
        cam = pts @ V[:3, :3].T + V[:3, 3]
        uv = cam @ K.T
        u, w = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
        col, row = u.floor().long(), w.floor().long()
        inside = (cam[:, 2] > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
        a = torch.zeros(pts.shape[0])
        a[inside] = alpha[b, row[inside], col[inside]]
        occ &= ~inside | (a > 0.3)
        c = torch.full((pts.shape[0], 3), float("nan"))
        c[inside] = v.images[b, row[inside], col[inside]]
        c[inside & (a <= 0.3)] = float("nan")
        colours.append(c)
    occ3 = occ.reshape(grid, grid, grid).float()
    empty_neigh = F.max_pool3d(1.0 - occ3[None, None], 3, 1, 1)[0, 0] > 0
    surface = (occ3 > 0) & empty_neigh
    blur = F.avg_pool3d(F.pad(occ3[None, None], (2,) * 6, mode="replicate"), 5, 1)[0, 0]
    gx, gy, gz = torch.gradient(blur)
    normal = -torch.stack([gx, gy, gz], -1)
    sel = surface.reshape(-1)
    n = F.normalize(normal.reshape(-1, 3)[sel].double(), dim=-1)
    med = torch.stack(colours, 0)[:, sel].nanmedian(0).values.nan_to_num(0.5)
    return {"means": pts[sel].float(), "normals": n.float(), "colours": med.float().clamp(0, 1),
            "voxel": 2 * bound / grid}


def run_task(run_dir: Path, overrides: list[str]) -> dict:
    t = time.perf_counter()
    run_config(ROOT / "configs" / "refine_room.yaml", run_dir, ["--device", "cpu", *overrides])
    init = json.loads((run_dir / "metrics_initial.json").read_text())
    final = json.loads((run_dir / "metrics_final.json").read_text())
    return {"run_dir": str(run_dir.relative_to(ROOT)), "initial": init, "final": final, "overrides": overrides,
            "wall_s": time.perf_counter() - t}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--grid", type=int, default=40)
    p.add_argument("--fit-steps", type=int, default=60)
    p.add_argument("--pose-steps", type=int, default=90)
    p.add_argument("--estimator", default="ht")
    args = p.parse_args()
    base = ROOT / "runs" / "bench-refine-lego"
    base.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    hull = carve(args.grid, args.resolution)
    scfg = SceneConfig(channels=3, learn=["means", "normals", "scales", "opacities", "features"], opacity=None,
                       scale=None)
    n = hull["means"].shape[0]
    scene = SurfelScene.from_points(scfg, hull["means"], hull["normals"], scales=0.6 * hull["voxel"],
                                    opacities=0.9, features=hull["colours"])
    scene.save_ply(base / "hull.ply")
    t_carve = time.perf_counter() - t0
    print(f"visual hull: {n} surface points ({args.grid}^3 grid), {t_carve:.1f} s")
    common = ["data.source=nerf", f"data.nerf.root={LEGO}", f"data.nerf.resolution={args.resolution}",
              f"data.nerf.limit={args.frames}", "render.background=[1.0,1.0,1.0]", "shading.model=albedo",
              f"render.estimator={args.estimator}", "filter.enabled=false", "log.images=0",
              "coverage_mask=0.0"]  # the white background is signal here (silhouettes)
    fit = run_task(base / "fit", common + [
        f"data.nerf.cloud={base / 'hull.ply'}", "data.nerf.rot_deg=0.0", "data.nerf.trans_frac=0.0",
        "poses.learn=false", f"optim.steps={args.fit_steps}", "optim.warmup=0",
        f"optim.decay_every={max(1, args.fit_steps // 2)}", f"log.checkpoint={args.fit_steps}"])
    pose = run_task(base / "pose", common + [
        f"data.nerf.cloud={base / 'fit' / 'scene.ply'}", "data.nerf.rot_deg=2.0", "data.nerf.trans_frac=0.02",
        "poses.learn=true", "scene.learn=[]", f"optim.steps={args.pose_steps}", "optim.warmup=0",
        f"optim.decay_every={max(1, args.pose_steps // 3)}", f"log.checkpoint={args.pose_steps}"])
    total = time.perf_counter() - t0
    out = {"args": vars(args), "hull_points": n, "carve_s": t_carve, "fit": fit, "pose": pose, "total_s": total}
    write_result("refine_lego", out)
    # before/after images: reference | before | after | |before-ref| | |after-ref|
    v = load_split(LEGO, "train", resolution=args.resolution, limit=args.frames)
    before = torch.load(base / "pose" / "renders_initial.pt")
    after = torch.load(base / "pose" / "renders_final.pt")
    IMAGES.mkdir(parents=True, exist_ok=True)
    for f in (0, args.frames // 2):
        ref = v.images[f]
        row = torch.cat([ref, before[f].clamp(0, 1), after[f].clamp(0, 1), (before[f] - ref).abs().clamp(0, 1),
                         (after[f] - ref).abs().clamp(0, 1)], 1)
        big = row.repeat_interleave(3, 0).repeat_interleave(3, 1)
        iio.imwrite(IMAGES / f"lego_pose_frame{f:02d}.png", (big.numpy() * 255).round().astype(np.uint8))
    i, f = pose["initial"], pose["final"]
    fi = fit["final"]
    print(f"scene fit (true poses): PSNR {fit['initial']['psnr']:.2f} -> {fi['psnr']:.2f}, "
          f"SSIM {fit['initial']['ssim']:.3f} -> {fi['ssim']:.3f}, {fi['seconds']:.0f} s")
    print(f"pose refinement: rot {i['rot_deg']:.3f} -> {f['rot_deg']:.3f} deg (/{i['rot_deg'] / f['rot_deg']:.1f}), "
          f"trans {i['trans']:.4f} -> {f['trans']:.4f} (/{i['trans'] / f['trans']:.1f}), "
          f"PSNR {i['psnr']:.2f} -> {f['psnr']:.2f}, SSIM {i['ssim']:.3f} -> {f['ssim']:.3f}, "
          f"{f['seconds']:.0f} s, peak RSS {f['peak_rss_mb']:.0f} MB; total {total:.0f} s")
    print(f"  relative pose error: rot {i['rpe_rot_deg']:.3f} -> {f['rpe_rot_deg']:.3f} deg "
          f"(/{i['rpe_rot_deg'] / f['rpe_rot_deg']:.1f}), trans {i['rpe_trans']:.4f} -> {f['rpe_trans']:.4f} "
          f"(/{i['rpe_trans'] / f['rpe_trans']:.1f}); common offset after {f['gauge_rot_deg']:.3f} deg / "
          f"{f['gauge_trans']:.4f}")


if __name__ == "__main__":
    main()

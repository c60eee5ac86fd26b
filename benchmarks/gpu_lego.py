"""The lego stage-1 step on a GPU (or the CPU): the sampler and one step, per resolution and views per call.

On the stage-1 start of ``configs/lego.yaml`` (the visual hull of its training silhouettes, about 78 500 surfels;
``--ply`` loads fitted surfels instead, e.g. a run's ``geometry.ply``) with the config's render settings
(``render.*``: m, ε, estimator, compositing, low-pass, culling), this times, per resolution (the training
cameras' intrinsics scaled to it) and per number of views rendered in one op call (the first ``B`` training views):

* **sampler**: :func:`nsplat.ops.project` + :func:`nsplat.ops.sample` of the ``B`` cameras (no gradients); on
  CUDA also, for the first ``--views`` count, once per threads-per-pixel setting of ``--lanes``
  (``NSPLAT_CUDA_PIXEL_LANES``, docs/op.md "CUDA lanes"), so that a GPU session can check the automatic choice;
* **step**: the stage-1 step through the public API, :func:`nsplat.ops.splat` forward of the ``B`` cameras in one
  call (a ``[B]`` seed tensor, one seed per camera) + the L1 loss against the training images (resized to the
  resolution) + its backward (no optimiser step). The features are each view's colour of the SH coefficients
  (:func:`nsplat.render.sh.view_colour`, as the fitter does), ``[N,3]`` for one view and per-camera ``[B,N,3]`` for
  several (one op call, camera ``b`` seeing its own colours); for several views the same step is also timed as ``B``
  one-view calls (the path before per-camera features), beside it. On CUDA one more step runs under
  ``torch.cuda.set_sync_debug_mode("warn")``: its device-to-host synchronisations, by source line, go to the JSON.

Each figure is the median over ``--repeats`` runs after two warm-up runs, each timed with
``torch.cuda.synchronize()`` before and after on CUDA (plain wall time on the CPU). The table puts the GPU
targets beside the step (one view ≤ 8 ms at 200² and ≤ 15 ms at 800², eight views ≤ 20 ms at 200²; they are
targets for an H100/H200, not for a CPU).

    python -m benchmarks.gpu_lego --device cuda                              # 200², 400², 800² × 1, 8 views
    python -m benchmarks.gpu_lego --device cuda --ply runs/lego/geometry.ply # fitted surfels
    python -m benchmarks.gpu_lego --device cpu --quick                       # 64², the procedural scene (< 1 min)

Lego data: ``$NSPLAT_DATA/nerf_synthetic/lego_400`` (``nsplat data fetch lego --resolution 400``, docs/data.md).
Writes ``benchmarks/results/gpu_lego-<device>.json`` (the GPU's name in ``machine.cuda``) and prints the table.
``.ci/gpu_check.sh``'s ``lego`` stage runs it on a lent GPU (docs/performance.md).
"""
from __future__ import annotations

import argparse
import itertools
import os
import statistics
import sys
import time
import warnings
from collections import Counter
from collections.abc import Callable

import torch
import torch.nn.functional as F

from benchmarks.common import REPO, markdown, write_result
from nsplat.config import load_config, read_yaml
from nsplat.ops import project, sample, splat
from nsplat.ops.validation import inclusion_for
from nsplat.render.sh import view_colour
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.data import load_views
from nsplat.tasks.neural.starts import initial_geometry

#: (resolution, views) → the issue's GPU target for the step, in ms.
TARGETS = {(200, 1): 8.0, (800, 1): 15.0, (200, 8): 20.0}
WARMUP = 2


def timer(device: torch.device, fn: Callable[[], object], repeats: int) -> list[float]:
    """Wall milliseconds of ``fn()`` over ``repeats`` runs after :data:`WARMUP` runs (CUDA: synchronised)."""
    cuda = device.type == "cuda"
    out = []
    for it in range(WARMUP + repeats):
        if cuda:
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        fn()
        if cuda:
            torch.cuda.synchronize(device)
        if it >= WARMUP:
            out.append(1000 * (time.perf_counter() - t0))
    return out


def host_syncs(device: torch.device, fn: Callable[[], object]) -> dict[str, int] | None:
    """The device-to-host synchronisations of one run of ``fn()`` on CUDA (``torch.cuda.set_sync_debug_mode``), by
    the Python line that caused them (``None`` on the CPU). Native code's syncs (the sampler reads sizes back) are
    reported at the line that called the op."""
    if device.type != "cuda":
        return None
    torch.cuda.synchronize(device)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            fn()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    return dict(Counter(f"{w.filename}:{w.lineno}" for w in caught if "synchroniz" in str(w.message)))


def parse_ints(text: str, what: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        raise SystemExit(f"{what}: expected a comma-separated list of positive integers, got {text!r}")
    return values


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=str(REPO / "configs" / "lego.yaml"))
    ap.add_argument("--ply", default=None, help="fitted surfels (a run's geometry.ply) instead of the config's start")
    ap.add_argument("--device", default="cuda", choices=["cpu", "cuda"])
    ap.add_argument("--resolutions", default="200,400,800", help="square image sides (default %(default)s)")
    ap.add_argument("--views", default="1,8", help="cameras per op call (default %(default)s)")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--lanes", default="1,2,4,8,16",
                    help="CUDA only: threads per pixel to time the sampler with, beside the automatic choice "
                         "(default %(default)s; '' for none)")
    ap.add_argument("--quick", action="store_true",
                    help="smoke size: configs/default.yaml's procedural scene with SH colour, 64², 3 repeats")
    args = ap.parse_args()
    if args.quick:
        args.config, args.resolutions, args.repeats = str(REPO / "configs" / "default.yaml"), "64", 3
    resolutions, view_counts = parse_ints(args.resolutions, "--resolutions"), parse_ints(args.views, "--views")
    lane_counts = parse_ints(args.lanes, "--lanes") if args.lanes and args.device == "cuda" else []
    if any(not 1 <= k <= 16 for k in lane_counts):
        raise SystemExit(f"--lanes: expected integers in [1, 16], got {args.lanes!r}")
    if args.repeats < 1:
        raise SystemExit(f"--repeats: expected >= 1, got {args.repeats}")
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: torch sees no CUDA device (use --device cpu)")
    overrides = ["geometry.init=ply", f"geometry.ply={args.ply}"] if args.ply else []
    if args.quick:  # the default scene with lego's view-dependent colour (SH degree 3)
        overrides += ["geometry.optim.shading=sh", "geometry.sh_degree=3"]
    cfg = load_config(Config, read_yaml(args.config), overrides)
    if cfg.geometry.optim.shading != "sh":
        raise SystemExit(f"{args.config}: this benchmark times the SH stage 1 (geometry.optim.shading: sh)")
    views = load_views(cfg, "train", torch.device("cpu"))
    if max(view_counts) > len(views):
        raise SystemExit(f"--views: at most the {len(views)} training views of {args.config}, got {max(view_counts)}")
    t0 = time.perf_counter()
    scene = initial_geometry(cfg, views, cfg.seed).to(device)
    start_s = time.perf_counter() - t0
    r = cfg.render
    settings = r.op_settings().kwargs()
    bg = views.background.to(device) if views.background is not None else None
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    result = f"gpu_lego-{device.type}"
    meta = {"config": args.config, "ply": args.ply, "quick": args.quick, "device": device.type, "gpu": name,
            "points": scene.num_points, "start_s": start_s, "render": settings, "repeats": args.repeats,
            "warmup": WARMUP}
    rows, records = [], []
    for res in resolutions:
        scale = res / views.width
        Ks_all = views.Ks.clone()
        Ks_all[:, :2] *= scale
        for B in view_counts:
            vm, Ks = views.viewmats[:B].to(device), Ks_all[:B].to(device)
            target = F.interpolate(views.images[:B].permute(0, 3, 1, 2), size=(res, res), mode="bilinear",
                                   antialias=True, align_corners=False).permute(0, 2, 3, 1).contiguous().to(device)
            calls = itertools.count()

            def seed() -> torch.Tensor:  # one seed per camera, new every call (made on the device: no copy)
                return torch.arange(B, dtype=torch.int64, device=device) + B * next(calls)

            @torch.no_grad()
            def sampler() -> None:
                proj = project(scene.means, scene.normals, scene.scales, scene.opacities, vm, Ks, near=r.near,
                               far=r.far, lowpass=r.lowpass, backface_cull=r.backface_cull)
                sample(proj, Ks, res, res, samples=r.samples, eps=r.eps, seed=seed(),
                       hermite_order=r.hermite_order, hermite_tol=r.hermite_tol,
                       inclusion=inclusion_for(r.estimator), stratified=r.stratified)

            def step() -> None:
                scene.zero_grad(set_to_none=True)
                feats = torch.stack([view_colour(scene.features, scene.means, vm[b]) for b in range(B)])
                feats = feats[0] if B == 1 else feats
                out = splat(scene.means, scene.normals, scene.scales, scene.opacities, feats, vm, Ks, res, res,
                            seed=seed(), background=bg, **settings)
                (out.image - target).abs().mean().backward()

            def step_loop() -> None:  # the same step as B one-view calls (how shaded views were rendered before)
                scene.zero_grad(set_to_none=True)
                first = B * next(calls)
                for b in range(B):
                    feats = view_colour(scene.features, scene.means, vm[b])
                    out = splat(scene.means, scene.normals, scene.scales, scene.opacities, feats, vm[b:b + 1],
                                Ks[b:b + 1], res, res, seed=first + b, background=bg, **settings)
                    ((out.image - target[b:b + 1]).abs().mean() / B).backward()

            sampler_ms, step_ms = timer(device, sampler, args.repeats), timer(device, step, args.repeats)
            lanes_ms = {}
            for k in lane_counts if B == view_counts[0] else []:  # the lanes split one camera's pixels
                os.environ["NSPLAT_CUDA_PIXEL_LANES"] = str(k)
                try:
                    lanes_ms[k] = statistics.median(timer(device, sampler, args.repeats))
                finally:
                    del os.environ["NSPLAT_CUDA_PIXEL_LANES"]
            loop_ms = timer(device, step_loop, args.repeats) if B > 1 else None
            syncs = host_syncs(device, step)
            rec = {"resolution": res, "views": B,
                   "features": "SH view colour" if B == 1 else "SH view colour per camera",
                   "sampler_ms": statistics.median(sampler_ms), "step_ms": statistics.median(step_ms),
                   "sampler_runs_ms": sampler_ms, "step_runs_ms": step_ms, "target_step_ms": TARGETS.get((res, B)),
                   "loop_step_ms": statistics.median(loop_ms) if loop_ms else None, "loop_step_runs_ms": loop_ms,
                   "step_host_syncs": syncs, "sampler_ms_by_lanes": lanes_ms}
            records.append(rec)
            write_result(result, {**meta, "rows": records})  # each row as it comes (a time limit keeps the rest)
            by_lanes = ", ".join(f"{k}: {v:.1f}" for k, v in lanes_ms.items())
            print(f"{res}² × {B} views: sampler {rec['sampler_ms']:.1f} ms (by lanes: {by_lanes or '-'}), "
                  f"step {rec['step_ms']:.1f} ms", file=sys.stderr, flush=True)
            target_txt = f"≤ {rec['target_step_ms']:g}" if rec["target_step_ms"] else "–"
            loop_txt = f"{rec['loop_step_ms']:.1f}" if loop_ms else "–"
            rows.append([f"{res}²", B, rec["features"], f"{rec['sampler_ms']:.1f}", f"{rec['step_ms']:.1f}",
                         target_txt, f"{rec['step_ms'] / B:.1f}", loop_txt])
    head = (f"{args.ply or args.config}: {scene.num_points} surfels, m = {r.samples}, estimator {r.estimator}, "
            f"{r.composite}, {name}{'' if device.type == 'cuda' else f', {torch.get_num_threads()} threads'}; "
            f"median of {args.repeats} (ms)")
    table = head + "\n\n" + markdown(["resolution", "views", "features", "sampler (project + sample)",
                                      "step (splat + L1 backward)", "GPU target (step)", "step per view",
                                      "step as B one-view calls"], rows)
    write_result(result, {**meta, "rows": records}, table)


if __name__ == "__main__":
    sys.exit(main())

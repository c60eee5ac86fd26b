"""Peak memory and step time of the sampled op against the truncated (DSS-like) renderer on a room-scale cloud
fused from a real RGB-D capture: the paper's memory claim (DSS had to drop 90 % of a SLAM cloud's points to fit an
8 GB GPU; the sampled op fits), measured on the CPU.

The cloud is fused (:func:`nsplat.data.fusion.fuse`) from every frame of the TUM sequence ``rgbd/tum_fr1_rpy_50``
at 640×480 along its odometry, once per point budget (``FusionConfig.max_points``: a larger budget is a finer merge
voxel; ``all`` is the finest the fusion makes, the median pixel footprint). Each cloud is rendered into one camera
(the middle frame) at each resolution by each renderer, ``nsplat.render.renderer.render`` with

* ``splat``: ``RenderConfig(renderer="splat", samples=40, eps=0.01, near=0.3)`` (the sampled op);
* ``truncated``: ``RenderConfig(renderer="truncated", composite="alpha", near=0.3)`` (kernels cut at 3σ, every
  (pixel, point) pair in range composited exactly, differentiated by autograd),

with opacities 0.9, the fused colours as features and the fused std-dev as both scales; one step is forward +
backward of the masked L1 loss (``nsplat.tasks.refine.optimisers.masked_l1``, the frame's valid pixels) against
the frame, every scene tensor requiring its gradient.

Each (cloud, resolution, renderer) runs in a fresh process, as ``benchmarks/op_memory_cpu.py`` measures: the inputs
are loaded, a tiny forward + backward runs (code pages, thread pools), the resident set size is read (baseline) and
its high-water mark reset, then one step runs; **peak** is the high-water mark (``VmHWM``) minus the baseline (GB:
10⁹ bytes). Before the step the process's address space is capped at its size plus ``--limit-gb``, so a step that
would need more fails with an allocation error (recorded as ``over-limit``, as is a step whose peak passes the
limit) instead of swapping or meeting the OOM killer; any other error (or a signal, or ``--timeout``) is recorded as
``failed`` with its last line. A renderer that does not finish ``ok`` at a resolution is not run on larger clouds
there. **Step time**: wall and CPU (process) seconds of that step, the median of 3 steps when it takes under
``REPEAT_UNDER_S``. The fusion runs in its own process first (its peak is several GB), the clouds and frames going
through a temporary folder. ``in view``: the cloud's points in front of the near plane that project into the frame.

Writes ``benchmarks/results/refine_memory.json`` and prints a Markdown table. The data: ``$NSPLAT_DATA`` or
``../shared/data`` beside the checkout (``--sequence`` names another folder with an ``odometry.txt``); when it is
missing the script says so in one line and exits 2.

    OMP_NUM_THREADS=2 python -m benchmarks.refine_memory        # 50k … 3.2M and all points, 320×240 and 640×480
    python -m benchmarks.refine_memory --points 50000 100000 --resolutions 320x240   # a small configuration
    python -m benchmarks.refine_memory --smoke                  # synthetic planes, tiny (CI; not a result)
"""
from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import os
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from benchmarks.common import REPO, markdown, write_result
from nsplat.data.fusion import FusionConfig, fuse
from nsplat.data.paths import data_root
from nsplat.data.rgbd import RGBDSequence, camera_of, load_frames, tum_files
from nsplat.render.renderer import RenderConfig, render
from nsplat.tasks.refine.optimisers import masked_l1

#: The renderers compared, by name.
RENDERERS: dict[str, RenderConfig] = {
    "splat": RenderConfig(renderer="splat", samples=40, eps=0.01, near=0.3),
    "truncated": RenderConfig(renderer="truncated", composite="alpha", near=0.3),
}
#: The sequence, relative to the data root.
SEQUENCE = "rgbd/tum_fr1_rpy_50"
#: The capture's frame size (the resolutions are it downscaled by an integer).
CAPTURE = (640, 480)
#: Point budgets of the full run (``all``: the finest fusion).
POINTS = ["50000", "100000", "200000", "400000", "800000", "1600000", "3200000", "all"]
RESOLUTIONS = ["320x240", "640x480"]
#: Opacity of every surfel.
OPACITY = 0.9
#: A step faster than this (seconds) is timed as the median of 3.
REPEAT_UNDER_S = 5.0
#: The warm-up renders the first points of the cloud at the frame's size divided by this.
WARM_POINTS, WARM_DIVISOR = 2000, 16
#: The smoke run: synthetic frames of this size, these budgets, a 2 GB limit.
SMOKE = {"size": (40, 30), "frames": 4, "points": ["300", "1000"], "limit_gb": 2.0, "timeout": 60}


# ---------------------------------------------------------------------------------------------- inputs
def synthetic_sequence(width: int, height: int, frames: int) -> RGBDSequence:
    """Posed depth frames of two planes (a wall at 2 m, the front of a box at 1.2 m over the middle) from a camera
    sliding sideways, with a colour ramp: the smoke run's stand-in for the capture."""
    f = float(width)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    v, u = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    rx, ry = (u - K[0, 2]) / f, (v - K[1, 2]) / f
    depths, c2w = [], []
    for b in range(frames):
        tx = 0.05 * b
        box = ((rx * 1.2 + tx).abs() <= 0.3) & ((ry * 1.2).abs() <= 0.3)
        depths.append(torch.where(box, 1.2, 2.0))
        pose = torch.eye(4, dtype=torch.float64)
        pose[0, 3] = tx
        c2w.append(pose)
    image = torch.stack([u / width, v / height, torch.full_like(u, 0.5)], -1)
    return RGBDSequence(image.expand(frames, -1, -1, -1).clone(), torch.stack(depths),
                        torch.ones(frames, height, width, dtype=torch.bool), K.expand(frames, 3, 3).clone(),
                        torch.stack(c2w), None, torch.arange(frames, dtype=torch.float64),
                        [f"{b:03d}" for b in range(frames)])


def sequence_places(arg: str | None) -> list[Path]:
    """Where the sequence folder may be: ``--sequence``, else ``SEQUENCE`` under ``$NSPLAT_DATA`` or, without it,
    under ``../shared/data`` beside the checkout and the user data folder."""
    if arg:
        return [Path(arg)]
    roots = [data_root()] if os.environ.get("NSPLAT_DATA") else [REPO.parent / "shared" / "data", data_root()]
    return [r / SEQUENCE for r in roots]


def parse_size(text: str) -> tuple[int, int]:
    """``"640x480"`` → ``(640, 480)``."""
    w, _, h = text.partition("x")
    return int(w), int(h)


def in_view(means: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
            near: float) -> int:
    """How many of ``means [N,3]`` lie beyond ``near`` and project into the ``width×height`` image."""
    cam = means @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    px = cam @ K.T
    u, v = px[:, 0] / z, px[:, 1] / z
    return int(((z > near) & (u >= 0) & (u < width) & (v >= 0) & (v < height)).sum())


def prepare(out: Path, points: list[str], sizes: list[str], sequence: Path | None, smoke: bool) -> None:
    """Fuse one cloud per budget and cut the middle frame at each size into ``out`` (``meta.json`` lists them)."""
    def frames(width: int, height: int) -> RGBDSequence:
        if smoke:
            return synthetic_sequence(width, height, SMOKE["frames"])
        files = tum_files(sequence, "odometry.txt", "", 0.02)
        return load_frames(files, camera_of("fr1", [], []), depth_scale=5000.0, depth_range=(0.1, 5.0),
                           downscale=CAPTURE[0] // width, progress=False)

    full = frames(*(SMOKE["size"] if smoke else CAPTURE))
    idx = len(full) // 2
    meta: dict[str, Any] = {"frame": full.names[idx], "frames": len(full), "clouds": [], "views": {}}
    views = {}
    for size in sizes:
        w, h = parse_size(size)
        seq = full if (w, h) == (full.width, full.height) else frames(w, h)
        views[size] = {"image": seq.images[idx:idx + 1], "mask": seq.valid[idx:idx + 1],
                       "viewmat": torch.linalg.inv(seq.c2w[idx:idx + 1]).float(), "K": seq.Ks[idx:idx + 1],
                       "width": w, "height": h}
        torch.save(views[size], out / f"view_{size}.pt")
        meta["views"][size] = str(out / f"view_{size}.pt")
    for budget in points:
        print(f"refine_memory: fusing {len(full)} frames with max_points={budget}", file=sys.stderr, flush=True)
        s = fuse(full.depths, full.images, full.Ks, full.c2w,
                 FusionConfig(max_points=10 ** 12 if budget == "all" else int(budget)), progress=False)
        path = out / f"cloud_{budget}.pt"
        torch.save({"means": s.means, "normals": s.normals, "colours": s.colours, "scales": s.scales}, path)
        meta["clouds"].append({"budget": budget, "points": int(s.means.shape[0]), "voxel": s.voxel,
                               "file": str(path), "in_view": {
                                   size: in_view(s.means, v["viewmat"][0], v["K"][0], v["width"], v["height"],
                                                 RENDERERS["splat"].near) for size, v in views.items()}})
    (out / "meta.json").write_text(json.dumps(meta))


# ---------------------------------------------------------------------------------------------- one measurement
def _status_kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"no {field} in /proc/self/status")


def _is_allocation_error(exc: BaseException) -> bool:
    text = str(exc)
    return isinstance(exc, MemoryError) or "can't allocate memory" in text or "bad_alloc" in text


def one(cloud_file: str, view_file: str, renderer: str, limit_gb: float) -> dict[str, Any]:
    """Measure one step of ``renderer`` on a cloud and a view (files of :func:`prepare`) in this process."""
    cfg = RENDERERS[renderer]
    cloud, view = torch.load(cloud_file), torch.load(view_file)
    N = cloud["means"].shape[0]
    params = [cloud["means"], cloud["normals"], cloud["scales"][:, None].repeat(1, 2),
              torch.full((N,), OPACITY), cloud["colours"]]
    params = [p.contiguous().requires_grad_() for p in params]
    W, H = view["width"], view["height"]

    def step(ps: list[torch.Tensor], K: torch.Tensor, width: int, height: int, target: torch.Tensor,
             mask: torch.Tensor, seed: int) -> tuple[float, float]:
        for p in ps:
            p.grad = None
        t0, c0 = time.perf_counter(), time.process_time()
        out = render(*ps, view["viewmat"], K, width, height, cfg, seed=seed)
        masked_l1(out.image, target, mask).backward()
        return time.perf_counter() - t0, time.process_time() - c0

    w, h = max(W // WARM_DIVISOR, 1), max(H // WARM_DIVISOR, 1)
    K_warm = view["K"].clone()
    K_warm[:, :2] /= W / w
    step([p.detach()[:WARM_POINTS].clone().requires_grad_() for p in params], K_warm, w, h,
         torch.zeros(1, h, w, 3), torch.ones(1, h, w, dtype=torch.bool), 0)
    gc.collect()
    base = _status_kb("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM to the current RSS
    limit = int(limit_gb * 1e9)
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    cap = _status_kb("VmSize") * 1024 + limit
    resource.setrlimit(resource.RLIMIT_AS, (cap if hard == resource.RLIM_INFINITY else min(cap, hard), hard))
    row: dict[str, Any] = {"points": N, "base_gb": base * 1024 / 1e9, "threads": torch.get_num_threads()}
    try:
        times = [step(params, view["K"], W, H, view["image"], view["mask"], 1)]
        peak = (_status_kb("VmHWM") - base) * 1024
        if times[0][0] < REPEAT_UNDER_S:
            times += [step(params, view["K"], W, H, view["image"], view["mask"], s) for s in (2, 3)]
    except Exception as exc:  # noqa: BLE001 - any failure of the step is the measurement's answer
        line = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        return {**row, "status": "over-limit" if _is_allocation_error(exc) else "failed",
                "error": f"{type(exc).__name__}: {line}"[:300],
                "peak_gb": (_status_kb("VmHWM") - base) * 1024 / 1e9}
    row.update(peak_gb=peak / 1e9, step_s=statistics.median(t for t, _ in times),
               cpu_s=statistics.median(c for _, c in times), steps_timed=len(times))
    if peak > limit:
        row.update(status="over-limit", error=f"peak {peak / 1e9:.2f} GB passes the {limit_gb:g} GB limit")
    else:
        row.update(status="ok", error="")
    return row


def measure(cloud: dict[str, Any], view_file: str, renderer: str, limit_gb: float, timeout: float) -> dict[str, Any]:
    """:func:`one` in a fresh process; a crash, a signal or the timeout becomes a ``failed`` row."""
    argv = [sys.executable, "-m", "benchmarks.refine_memory", "--one", cloud["file"], view_file, renderer,
            "--limit-gb", str(limit_gb)]
    row = {"points": cloud["points"]}
    try:
        proc = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {**row, "status": "failed", "error": f"timed out after {timeout:g} s"}
    lines = proc.stdout.strip().splitlines()
    if proc.returncode == 0 and lines:
        return json.loads(lines[-1])
    tail = (proc.stderr.strip().splitlines() or [""])[-1][:300]
    how = f"killed by {signal.Signals(-proc.returncode).name}" if proc.returncode < 0 else \
        f"exit status {proc.returncode}"
    return {**row, "status": "failed", "error": f"{how}: {tail}" if tail else how}


# ---------------------------------------------------------------------------------------------- the sweep
def table(rows: list[dict[str, Any]]) -> str:
    """The Markdown table of the rows."""
    def num(r: dict[str, Any], key: str, fmt: str) -> str:
        return format(r[key], fmt) if r.get(key) is not None else "–"

    return markdown(["points", "in view", "resolution", "renderer", "peak GB", "step s (wall)", "CPU s", "status"],
                    [[r["points"], r["in_view"], r["resolution"], r["renderer"], num(r, "peak_gb", ".2f"),
                      num(r, "step_s", ".2f"), num(r, "cpu_s", ".2f"),
                      r["status"] + (f" ({r['error']})" if r["error"] else "")] for r in rows])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--points", nargs="+", default=POINTS, metavar="BUDGET",
                   help="fusion point budgets, ascending ('all': the finest fusion)")
    p.add_argument("--resolutions", nargs="+", default=RESOLUTIONS, metavar="WxH",
                   help=f"render sizes, the capture's {CAPTURE[0]}x{CAPTURE[1]} divided by an integer")
    p.add_argument("--renderers", nargs="+", default=list(RENDERERS), choices=list(RENDERERS))
    p.add_argument("--limit-gb", type=float, default=16.0, help="peak memory past which a renderer stops growing")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds one measurement may take")
    p.add_argument("--sequence", help=f"the RGB-D sequence folder (default: <data root>/{SEQUENCE})")
    p.add_argument("--smoke", action="store_true", help="synthetic planes, tiny (CI; not a result, nothing written)")
    p.add_argument("--one", nargs=3, metavar=("CLOUD", "VIEW", "RENDERER"), help=argparse.SUPPRESS)
    p.add_argument("--prepare", metavar="DIR", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.one:
        print(json.dumps(one(*args.one, args.limit_gb)))
        return 0
    if args.smoke:
        args.points, args.limit_gb, args.timeout = SMOKE["points"], SMOKE["limit_gb"], SMOKE["timeout"]
        args.resolutions = ["x".join(map(str, SMOKE["size"]))]
    places = [] if args.smoke else sequence_places(args.sequence)
    sequence = next((s for s in places if s.is_dir()), None)
    if args.prepare:
        prepare(Path(args.prepare), args.points, args.resolutions, sequence, args.smoke)
        return 0
    if sequence is None and not args.smoke:
        print(f"refine_memory: no RGB-D sequence at {' or '.join(map(str, places))} (set $NSPLAT_DATA, or fetch "
              f"one with 'nsplat data fetch tum_fr1_rpy' and pass --sequence)", file=sys.stderr)
        return 2
    for size in args.resolutions if not args.smoke else []:
        w, h = parse_size(size)
        if CAPTURE[0] % w or CAPTURE[0] * h != CAPTURE[1] * w:
            p.error(f"--resolutions: {size} is not {CAPTURE[0]}x{CAPTURE[1]} divided by an integer")
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="nsplat-refine-memory-") as tmp:
        prep = [sys.executable, "-m", "benchmarks.refine_memory", "--prepare", tmp, "--points", *args.points,
                "--resolutions", *args.resolutions, *(["--smoke"] if args.smoke else ["--sequence", str(sequence)])]
        subprocess.run(prep, cwd=REPO, check=True)
        meta = json.loads((Path(tmp) / "meta.json").read_text())
        growing = {(size, r) for size in args.resolutions for r in args.renderers}
        previous = None
        for cloud in meta["clouds"]:
            if cloud["points"] == previous:  # the budget is past what the capture gives
                continue
            previous = cloud["points"]
            for size in args.resolutions:
                for renderer in args.renderers:
                    if (size, renderer) not in growing:
                        continue
                    r = measure(cloud, meta["views"][size], renderer, args.limit_gb, args.timeout)
                    r = {"renderer": renderer, "resolution": size, "budget": cloud["budget"],
                         "voxel": cloud["voxel"], "in_view": cloud["in_view"][size], "peak_gb": None,
                         "step_s": None, "cpu_s": None, **r}
                    rows.append(r)
                    print(f"refine_memory: {renderer} {size} {r['points']} points: {r['status']} "
                          f"{r['error']}", file=sys.stderr, flush=True)
                    if r["status"] != "ok":
                        growing.discard((size, renderer))
    text = table(rows)
    if args.smoke:
        print(text)
        return 0
    write_result("refine_memory", {
        "command": "python -m benchmarks.refine_memory " + " ".join(
            ["--points", *args.points, "--resolutions", *args.resolutions, "--renderers", *args.renderers,
             "--limit-gb", f"{args.limit_gb:g}", "--timeout", f"{args.timeout:g}"]),
        "sequence": str(sequence), "frame": meta["frame"], "frames_fused": meta["frames"],
        "fusion": dataclasses.asdict(FusionConfig()) | {"max_points": "per row (budget)"},
        "renderers": {name: dataclasses.asdict(cfg) for name, cfg in RENDERERS.items()},
        "opacity": OPACITY, "limit_gb": args.limit_gb, "repeat_under_s": REPEAT_UNDER_S,
        "rows": rows, "markdown": text}, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

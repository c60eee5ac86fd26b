"""Fusion time and peak memory against the number of frames: does the streaming fusion
(:class:`nsplat.data.fusion.SurfelMap`) hold a whole sequence, and a simulated 2,500-frame one, in bounded memory
and linear time?

The frames: ``rgbd/tum_fr1_rpy_10hz`` (232 real 640×480 TUM frames, every 3rd of freiburg1_rpy) posed by its
motion-capture ground truth (nearest timestamp; this benchmark scores nothing, the poses only place the frames).
Frame ``i`` is real frame ``i mod 232``; from the second pass on its pose is jittered (a seeded rotation of
``JITTER_DEG`` degrees about a random axis and a translation of ``JITTER_M`` metres in each axis, std-devs), so
a repeated frame lands partly in new voxels, as a longer capture of the same room would. Each frame is decoded
from disk when it is fused (nothing but the map and one frame is held); at 320×240 the colour is averaged over
2×2 blocks and the depth downscaled as the loader does (``nsplat.data.rgbd.downscale_depth``), the intrinsics
halved; depth outside ``DEPTH_RANGE`` is invalid; no undistortion (it changes neither the time nor the memory
materially).

Each (resolution, frame count) runs in a fresh process (``torch`` on ``--threads`` threads, default 1: on a
2-core machine shared with other work, two OpenMP threads on a busy core made the same fusion up to 10× slower):
**peak** is the process's high-water mark of its resident set (``ru_maxrss``, GB = 10⁹ bytes), which includes the
interpreter and torch (``base``: the resident set after the imports); **time** is the wall time of the fusion loop
(decoding included, ``decode`` its share) and **CPU** its process CPU time (the steadier figure on a shared
machine), **per frame** its mean. ``former`` is what the fusion before it streamed
would have held at once: 96 bytes per candidate (float64 position, normal, colour, radius, weight and an int64
frame index per valid pixel) plus a bool per (voxel, frame) pair — computed from the counts, not run.

Writes ``benchmarks/results/fusion_scaling.json`` (rows of other sizes already there with the same settings are
kept, so the resolutions can run separately) and prints a Markdown table. The data: ``$NSPLAT_DATA`` or
``../shared/data`` beside the checkout (``--sequence`` names another TUM-layout folder with a ``groundtruth.txt``);
when it is missing the script says so in one line and exits 2.

    python -m benchmarks.fusion_scaling                      # 50, 232, 2500 frames at 640×480 and 320×240 (~10 min)
    python -m benchmarks.fusion_scaling --frames 50 232 --resolutions 320x240
    python -m benchmarks.fusion_scaling --smoke              # synthetic frames, tiny (CI; not a result)
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from benchmarks.common import REPO, markdown, read_result, write_result
from nsplat.data.paths import data_root

#: The sequence, relative to the data root.
SEQUENCE = "rgbd/tum_fr1_rpy_10hz"
#: Freiburg 1 RGB intrinsics at 640×480 (the sequence's README).
FX, FY, CX, CY = 517.3, 516.5, 318.6, 255.3
DEPTH_SCALE = 5000.0
#: Valid depth (metres), as ``configs/refine_tum.yaml``'s ``data.rgbd.depth_range``.
DEPTH_RANGE = (0.1, 5.0)
FRAMES = [50, 232, 2500]
RESOLUTIONS = ["640x480", "320x240"]
#: Pose jitter of the repeated frames: rotation (degrees) and translation (metres per axis), std-devs.
JITTER_DEG, JITTER_M = 1.0, 0.02
#: Bytes per candidate the former batch fusion held (float64 points, normals, colours [3], radius, weight; int64
#: frame).
FORMER_BYTES = 8 * (3 + 3 + 3 + 1 + 1 + 1)
#: The smoke run: synthetic frames of this size and these counts.
SMOKE = {"size": (64, 48), "frames": [5, 20]}


def _list(path: Path) -> list[tuple[float, str]]:
    """A TUM ``rgb.txt`` / ``depth.txt``: ``(timestamp, file)`` per line."""
    out = []
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            ts, name = line.split()[:2]
            out.append((float(ts), name))
    return out


def _quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternions ``[T,4]`` (x, y, z, w) → rotation matrices ``[T,3,3]``."""
    x, y, z, w = (q / q.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)


def tum_sequence(root: Path) -> tuple[list[str], list[str], torch.Tensor]:
    """The colour and depth files (paired by line) and each pair's camera → world pose ``[B,4,4]`` (float64) from
    ``groundtruth.txt`` (nearest timestamp)."""
    rgb, depth = _list(root / "rgb.txt"), _list(root / "depth.txt")
    rows = [[float(v) for v in line.split()] for line in (root / "groundtruth.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    gt = torch.tensor(rows, dtype=torch.float64)
    ts = torch.tensor([t for t, _ in rgb], dtype=torch.float64)
    j = (ts[:, None] - gt[None, :, 0]).abs().argmin(1)
    c2w = torch.eye(4, dtype=torch.float64).repeat(len(rgb), 1, 1)
    c2w[:, :3, :3] = _quat_to_matrix(gt[j, 4:8])
    c2w[:, :3, 3] = gt[j, 1:4]
    return [str(root / n) for _, n in rgb], [str(root / n) for _, n in depth], c2w


def _jitter(i: int) -> torch.Tensor:
    """The seeded pose jitter ``[4,4]`` of frame ``i``."""
    g = torch.Generator().manual_seed(i)
    axis = torch.randn(3, generator=g, dtype=torch.float64)
    angle = math.radians(JITTER_DEG) * float(torch.randn(1, generator=g, dtype=torch.float64))
    a = axis / axis.norm()
    A = torch.tensor([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]], dtype=torch.float64)
    E = torch.eye(4, dtype=torch.float64)
    E[:3, :3] = torch.eye(3, dtype=torch.float64) + math.sin(angle) * A + (1 - math.cos(angle)) * A @ A
    E[:3, 3] = JITTER_M * torch.randn(3, generator=g, dtype=torch.float64)
    return E


def frame_stream(root: Path, frames: int, downscale: int,
                 timing: dict[str, float]) -> Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """``frames`` frames ``(depth [H,W] m, image [H,W,3] in [0,1], K [3,3], c2w [4,4])`` decoded one at a time
    (the sequence repeated, the repeats' poses jittered); adds the decoding seconds to ``timing["decode"]``."""
    import imageio.v3 as iio

    from nsplat.data.rgbd import downscale_depth

    rgb, depth, c2w = tum_sequence(root)
    K = torch.tensor([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])
    K[:2] /= downscale
    for i in range(frames):
        t0 = time.perf_counter()
        j = i % len(rgb)
        d = torch.from_numpy(iio.imread(depth[j]).astype("float32")) / DEPTH_SCALE
        d = torch.where((d >= DEPTH_RANGE[0]) & (d <= DEPTH_RANGE[1]), d, torch.zeros_like(d))
        im = torch.from_numpy(iio.imread(rgb[j])[..., :3]).float() / 255.0
        if downscale > 1:
            d = downscale_depth(d, downscale)
            im = torch.nn.functional.avg_pool2d(im.permute(2, 0, 1)[None], downscale)[0].permute(1, 2, 0)
        pose = c2w[j] if i < len(rgb) else c2w[j] @ _jitter(i)
        timing["decode"] += time.perf_counter() - t0
        yield d, im, K, pose


def synthetic_stream(frames: int, timing: dict[str, float]) -> Iterator[tuple[torch.Tensor, ...]]:
    """The smoke run's frames: a wall at 2 m and a box face at 1.2 m from a camera sliding sideways."""
    W, H = SMOKE["size"]
    K = torch.tensor([[float(W), 0.0, W / 2], [0.0, float(W), H / 2], [0.0, 0.0, 1.0]])
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    rx, ry = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    image = torch.stack([u / W, v / H, torch.full_like(u, 0.5)], -1)
    for i in range(frames):
        tx = 0.02 * i
        box = ((rx * 1.2 + tx).abs() <= 0.3) & ((ry * 1.2).abs() <= 0.3)
        pose = torch.eye(4, dtype=torch.float64)
        pose[0, 3] = tx
        yield torch.where(box, 1.2, 2.0), image, K, pose


def _rss_gb() -> float:
    """This process's resident set now (GB)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024 / 1e9
    return float("nan")


def one(sequence: str | None, frames: int, resolution: str, voxel: float, max_points: int,
        threads: int) -> dict[str, Any]:
    """One fusion in this process; returns its figures (run by :func:`main` in a fresh process)."""
    from nsplat.data.fusion import FusionConfig, SurfelMap

    torch.set_num_threads(threads)
    base = _rss_gb()
    timing = {"decode": 0.0}
    if sequence is None:
        stream = synthetic_stream(frames, timing)
    else:
        downscale = 640 // int(resolution.partition("x")[0])
        stream = frame_stream(Path(sequence), frames, downscale, timing)
    fmap = SurfelMap(FusionConfig(voxel=voxel, max_points=max_points))
    largest = 0
    t0, c0 = time.perf_counter(), time.process_time()
    for frame in stream:
        fmap.add(*frame)
        largest = max(largest, len(fmap))
    s = fmap.surfels()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9
    return {"frames": frames, "resolution": resolution, "wall_s": round(wall, 2), "cpu_s": round(cpu, 2),
            "decode_s": round(timing["decode"], 2), "per_frame_s": round(wall / frames, 4),
            "peak_rss_gb": round(peak, 3), "base_rss_gb": round(base, 3), "surfels": int(s.means.shape[0]),
            "largest_map": largest, "map_mb": round(fmap.nbytes / 1e6, 1), "voxel": fmap.voxel,
            "doublings": fmap.doublings, "candidates": fmap.candidates,
            "former_gb": round((fmap.candidates * FORMER_BYTES + len(fmap) * frames) / 1e9, 2),
            "threads": threads}


def _table(results: list[dict[str, Any]]) -> str:
    """The Markdown table of the runs."""
    header = ["resolution", "frames", "wall (s)", "CPU (s)", "CPU per frame (ms)", "decode (s)", "peak RSS (GB)",
              "base (GB)", "surfels", "voxel (cm)", "map (MB)", "former (GB)"]
    rows = [[r["resolution"], r["frames"], r["wall_s"], r["cpu_s"], round(1000 * r["cpu_s"] / r["frames"], 1),
             r["decode_s"], r["peak_rss_gb"], r["base_rss_gb"], r["surfels"], round(100 * r["voxel"], 2),
             r["map_mb"], r["former_gb"]] for r in results]
    return markdown(header, rows)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, nargs="+", default=FRAMES)
    p.add_argument("--resolutions", nargs="+", default=RESOLUTIONS, choices=RESOLUTIONS)
    p.add_argument("--voxel", type=float, default=None, help="FusionConfig.voxel (default: FusionConfig's)")
    p.add_argument("--max-points", type=int, default=None, help="FusionConfig.max_points (default: FusionConfig's)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--sequence", help=f"a TUM-layout folder (default: $NSPLAT_DATA/{SEQUENCE})")
    p.add_argument("--name", default="fusion_scaling", help="the result's name (benchmarks/results/NAME.json)")
    p.add_argument("--smoke", action="store_true", help="synthetic frames, tiny (checks the script runs)")
    p.add_argument("--report", action="store_true", help="print the table of the written result and exit")
    p.add_argument("--one", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.report:
        earlier = read_result(args.name)
        print(_table(earlier["results"]) if earlier else f"no result {args.name}")
        return 0 if earlier else 2
    from nsplat.data.fusion import FusionConfig

    defaults = FusionConfig()
    voxel = defaults.voxel if args.voxel is None else args.voxel
    max_points = defaults.max_points if args.max_points is None else args.max_points
    if args.one:
        job = json.loads(args.one)
        print("RESULT " + json.dumps(one(job["sequence"], job["frames"], job["resolution"], voxel, max_points,
                                         args.threads)))
        return 0
    sequence: str | None = None
    frames, resolutions = args.frames, args.resolutions
    if args.smoke:
        frames, resolutions = SMOKE["frames"], ["x".join(map(str, SMOKE["size"]))]
    else:
        roots = [Path(args.sequence)] if args.sequence else \
            ([data_root()] if os.environ.get("NSPLAT_DATA") else [REPO.parent / "shared" / "data", data_root()])
        places = roots if args.sequence else [r / SEQUENCE for r in roots]
        found = [q for q in places if (q / "groundtruth.txt").is_file()]
        if not found:
            print(f"fusion_scaling: no sequence with a groundtruth.txt at {', '.join(map(str, places))}",
                  file=sys.stderr)
            return 2
        sequence = str(found[0])
    results = []
    for res in resolutions:
        for n in frames:
            job = json.dumps({"sequence": sequence, "frames": n, "resolution": res})
            cmd = [sys.executable, "-m", "benchmarks.fusion_scaling", "--one", job, "--threads", str(args.threads),
                   "--voxel", str(voxel), "--max-points", str(max_points)]
            env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
            out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=env)
            line = [x for x in out.stdout.splitlines() if x.startswith("RESULT ")]
            if out.returncode != 0 or not line:
                print(out.stderr[-2000:], file=sys.stderr)
                raise RuntimeError(f"fusion_scaling: {n} frames at {res} failed ({out.returncode})")
            r = json.loads(line[0][len("RESULT "):])
            print(f"{res} {n} frames: {r['wall_s']} s, peak {r['peak_rss_gb']} GB", file=sys.stderr)
            results.append(r)
    if not args.smoke and (earlier := read_result(args.name)) and earlier.get("voxel") == voxel and \
            earlier.get("max_points") == max_points:  # runs of other sizes with the same settings stay
        done = {(r["resolution"], r["frames"]) for r in results}
        results = [r for r in earlier["results"] if (r["resolution"], r["frames"]) not in done] + results
        results.sort(key=lambda r: (-int(r["resolution"].partition("x")[0]), r["frames"]))
    table = _table(results)
    if not args.smoke or os.environ.get("NSPLAT_BENCH_OUT"):
        write_result(args.name, {"sequence": sequence and SEQUENCE, "voxel": voxel, "max_points": max_points,
                                 "jitter": {"deg": JITTER_DEG, "m": JITTER_M}, "results": results}, table)
    else:
        print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())

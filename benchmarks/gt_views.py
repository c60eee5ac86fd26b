"""How long does rendering the reconstruction task's ground truth take, and how close is it to the dense oracle?

For each shape, the training and held-out GT views of its shipped config (``configs/reconstruct_<shape>.yaml``:
its views, resolution and held-out render count) are rendered into an empty cache with the tiled renderer
(``data.gt_tol``), timed in wall and CPU seconds. One view is also rendered with the dense oracle, for its time
and the largest difference between the two images.

    python -m benchmarks.gt_views                       # the four DSS shapes at the shipped configs
    python -m benchmarks.gt_views --shapes bunny --set data.width=256 data.height=256 data.views=124
    python -m benchmarks.gt_views --smoke               # bunny, 8 views at 64² (CI)
"""
from __future__ import annotations

import argparse
import tempfile
import time

import torch

from benchmarks.common import REPO, markdown, write_result
from nsplat.config import load_config, read_yaml
from nsplat.data.pointclouds import load_shape
from nsplat.ops import splat_dense
from nsplat.render.shading import lambert
from nsplat.tasks.reconstruct import Config
from nsplat.tasks.reconstruct_views import HELDOUT_OFFSET, cached_gt_images, gt_scene, view_cameras


def measure(shape: str, overrides: list[str], dense: bool) -> dict:
    """Times of one shape's GT views (and of one dense view)."""
    cfg = load_config(Config, read_yaml(REPO / "configs" / f"reconstruct_{shape}.yaml"), overrides)
    data, rc = cfg.data, cfg.render
    pc = load_shape(data.shape, data.root or None)
    with tempfile.TemporaryDirectory(prefix="nsplat-gt-") as cache:
        data.cache_dir = cache
        t0, c0 = time.perf_counter(), time.process_time()
        images, _, _, _ = cached_gt_images(pc, data, rc, data.views)
        held, _, _, _ = cached_gt_images(pc, data, rc, cfg.heldout, offset=HELDOUT_OFFSET, tag="heldout")
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    row = {"shape": shape, "points": pc.points.shape[0], "views": data.views, "heldout": cfg.heldout,
           "resolution": [data.width, data.height], "gt_tol": data.gt_tol, "wall_s": wall, "cpu_s": cpu}
    if dense:
        V, K = view_cameras(1, pc, data)
        gt = gt_scene(pc, data)
        t0 = time.perf_counter()
        ref = splat_dense(gt["means"], gt["normals"], gt["scales"], gt["opacities"],
                          lambert(gt["albedo"], gt["normals"], V), V, K, data.width, data.height,
                          near=rc.near, far=rc.far, lowpass=rc.lowpass).image
        row["dense_view_s"] = time.perf_counter() - t0
        row["max_abs_diff"] = float((ref - images[:1]).abs().max())
    return row


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--shapes", nargs="+", default=["bunny", "teapot", "yoga1", "yoga6"])
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides for every shape")
    p.add_argument("--no-dense", action="store_true", help="skip the dense view (about a minute at 256²)")
    p.add_argument("--smoke", action="store_true", help="bunny, 8 views at 64², no dense view")
    p.add_argument("--name", default="gt_views")
    args = p.parse_args()
    shapes, overrides = args.shapes, list(args.set)
    if args.smoke:
        shapes, overrides = ["bunny"], ["data.views=8", "data.width=64", "data.height=64", "heldout=1", "renders=1"]
    rows = [measure(s, overrides, dense=not (args.no_dense or args.smoke)) for s in shapes]
    table = markdown(["shape", "points", "views (train + held-out)", "resolution", "wall s", "CPU s",
                      "dense s/view", "max |tiled − dense|"],
                     [[r["shape"], r["points"], f"{r['views']} + {r['heldout']}", "×".join(map(str, r["resolution"])),
                       f"{r['wall_s']:.1f}", f"{r['cpu_s']:.1f}", f"{r.get('dense_view_s', float('nan')):.1f}",
                       f"{r.get('max_abs_diff', float('nan')):.1e}"] for r in rows])
    if args.smoke:
        print(table)
        return 0
    write_result(args.name, {"command": "python -m benchmarks.gt_views " + " ".join(
        [f"--shapes {' '.join(args.shapes)}"] + (["--set", *args.set] if args.set else [])), "threads":
        torch.get_num_threads(), "rows": rows}, table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

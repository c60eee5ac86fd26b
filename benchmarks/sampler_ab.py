"""The sampler of today's build against an earlier build's, in one process (A/B).

The earlier build (``--base``, default the commit before the tile-lane sampler) is compiled from its own
``ops/csrc`` (``git archive``) as a second extension module; both sample the same projected surfels of the same
views with the same settings and seeds, calls interleaved (A, B, A, B, ...), on 1 and on 2 threads. Reported per
scene and thread count: median wall and process CPU milliseconds per view, the ratio (base / today), and the exact
kernel evaluations per covered pixel of each (today's build counts the evaluations of a pixel's lane while it
searches). The draws of the two builds differ (the random number scheme changed with the sampler), so their
samples are compared in law by the tests, not here.

Scenes: ``default`` — the main job's stage-1 surfels (configs/default.yaml, ``--default-ply``), 64²; ``lego`` — the
fitted surfels of configs/lego_splat_only.yaml (``--lego-ply``), 200². Both with their config's render settings
(m = 40, eps = 0.01, low-pass 0.3).

    python train.py --run runs/default                                                       # ~2 min
    python train.py --config configs/lego_splat_only.yaml --run runs/lego_splat_only          # ~15 min
    python -m benchmarks.sampler_ab                      # ~3 min (+ about a minute to build the base once)
    python -m benchmarks.sampler_ab --scenes default --threads 1 --reps 3

Writes ``benchmarks/results/sampler_ab.json``.
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import tarfile
import tempfile
import time
from pathlib import Path
from types import ModuleType

import torch

from benchmarks.common import REPO, markdown, write_result
from nsplat.config import load_config, read_yaml
from nsplat.ops import project, sampler_isa
from nsplat.ops.build import backend, build_dir, cxx_standard
from nsplat.ops.library import camera_streams
from nsplat.scene import SurfelScene
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.data import load_views
from nsplat.tasks.neural.geometry import geometry_scene_config

#: The build the issue measured ("today's build" when the tile-lane sampler was written).
DEFAULT_BASE = "5a3af74"
SCENES = {"default": ("configs/default.yaml", "runs/default/geometry.ply"),
          "lego": ("configs/lego_splat_only.yaml", "runs/lego_splat_only/geometry.ply")}


def base_module(rev: str) -> ModuleType:
    """The CPU extension of commit ``rev`` (its ``ops/csrc``, its flags), built once into its own cache folder."""
    from torch.utils.cpp_extension import load

    out = build_dir(f"ab-{rev}")
    src = out / "csrc"
    if not (src / "cpu" / "splat_cpu.cpp").is_file():
        with tempfile.TemporaryDirectory() as tmp:
            tar = Path(tmp) / "csrc.tar"
            subprocess.run(["git", "archive", "-o", str(tar), rev, "ops/csrc"], cwd=REPO, check=True)
            with tarfile.open(tar) as t:
                t.extractall(tmp)
            (Path(tmp) / "ops" / "csrc").rename(src)
    sources = [str(p) for p in sorted((src / "cpu").glob("*.cpp"))]
    return load(name=f"nsplat_cpu_{rev}", sources=sources, extra_include_paths=[str(src)],
                extra_cflags=["-O3", "-fopenmp", f"-std={cxx_standard()}"], extra_ldflags=["-fopenmp"], build_directory=str(out),
                verbose=False)


def scene_inputs(name: str, ply: Path, views: int) -> tuple[list[list[torch.Tensor]], torch.Tensor, int, int, dict]:
    """The native sampler's inputs (projected surfels of each of the first ``views`` training views)."""
    config, _ = SCENES[name]
    cfg = load_config(Config, read_yaml(REPO / config), [])
    train = load_views(cfg, "train", torch.device("cpu"))
    scene = SurfelScene.load_ply(ply, geometry_scene_config(cfg), device=torch.device("cpu"))
    r = cfg.render
    inputs = []
    with torch.no_grad():
        for v in range(min(views, len(train))):
            vm, K = train.viewmats[v:v + 1], train.Ks[v:v + 1]
            p = project(scene.means, scene.normals, scene.scales, scene.opacities, vm, K, near=r.near, far=r.far,
                        lowpass=r.lowpass, backface_cull=r.backface_cull)
            inputs.append([t.contiguous() for t in (p.means2d, p.conics, p.amps, p.sigma2, p.normals_cam,
                                                     p.plane_offsets, p.depths)] + [K.contiguous()])
    settings = {"points": scene.num_points, "samples": r.samples, "eps": r.eps, "hermite_order": r.hermite_order,
                "hermite_tol": r.hermite_tol, "lowpass": r.lowpass}
    return inputs, train.Ks, train.width, train.height, settings


def measure(modules: dict[str, ModuleType], inputs: list, width: int, height: int, s: dict, reps: int) -> dict:
    """Interleaved calls of each module's ``sample`` on every view: per module, per-view wall/CPU ms (medians over
    reps) and evaluations per covered pixel."""
    def call(mod: ModuleType, args: list, seed: int) -> list:
        if mod is modules.get("base"):  # the base tree's sampler takes one seed for all cameras
            return mod.sample(*args, width, height, s["samples"], s["eps"], seed, s["hermite_order"],
                              s["hermite_tol"], 0, False)
        return mod.sample(*args, camera_streams(torch.tensor(seed), 1), width, height, s["samples"], s["eps"],
                          s["hermite_order"], s["hermite_tol"], 0, False)

    for name, mod in modules.items():  # warm-up (thread pools, caches)
        call(mod, inputs[0], 0)
    wall = {n: [] for n in modules}
    cpu_t = {n: [] for n in modules}
    work = {n: [] for n in modules}
    for rep in range(reps):
        for name, mod in modules.items():
            w0, c0 = time.perf_counter(), time.process_time()
            outs = [call(mod, args, rep + 1) for args in inputs]
            wall[name].append((time.perf_counter() - w0) / len(inputs))
            cpu_t[name].append((time.process_time() - c0) / len(inputs))
            work[name] += [float(o[3][o[2] > 0].double().mean()) for o in outs]
    return {n: {"wall_ms": 1e3 * statistics.median(wall[n]), "cpu_ms": 1e3 * statistics.median(cpu_t[n]),
                "evals_per_covered_px": statistics.mean(work[n])} for n in modules}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", default=DEFAULT_BASE, help="the earlier build's commit (default %(default)s)")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--default-ply", type=Path, default=REPO / SCENES["default"][1])
    ap.add_argument("--lego-ply", type=Path, default=REPO / SCENES["lego"][1])
    ap.add_argument("--threads", nargs="+", type=int, default=[2, 1])
    ap.add_argument("--views", type=int, default=4, help="training views sampled per repetition")
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args()
    plies = {"default": args.default_ply, "lego": args.lego_ply}
    for name in args.scenes:
        if not plies[name].is_file():
            config = SCENES[name][0]
            ap.error(f"--{name}-ply: {plies[name]} not found; train it first: python train.py --config {config} "
                     f"--run {plies[name].parent}")
    modules = {"base": base_module(args.base), "today": backend(torch.device("cpu"))}
    rows, records = [], []
    for name in args.scenes:
        inputs, _, width, height, settings = scene_inputs(name, plies[name], args.views)
        for threads in args.threads:
            torch.set_num_threads(threads)
            res = measure(modules, inputs, width, height, settings, args.reps)
            b, t = res["base"], res["today"]
            records.append({"scene": name, "threads": threads, "width": width, "height": height, **settings,
                            "results": res, "speedup_wall": b["wall_ms"] / t["wall_ms"],
                            "speedup_cpu": b["cpu_ms"] / t["cpu_ms"]})
            rows.append([name, f"{settings['points']}", f"{width}x{height}", threads,
                         f"{b['wall_ms']:.1f} / {b['cpu_ms']:.1f}", f"{t['wall_ms']:.1f} / {t['cpu_ms']:.1f}",
                         f"**{b['wall_ms'] / t['wall_ms']:.2f}x** / {b['cpu_ms'] / t['cpu_ms']:.2f}x",
                         f"{b['evals_per_covered_px']:.0f} / {t['evals_per_covered_px']:.0f}"])
    table = markdown(["scene", "N", "res", "threads", f"base {args.base} ms (wall / CPU)", "today ms (wall / CPU)",
                      "speed-up (wall / CPU)", "evals per covered px (base / today)"], rows)
    write_result("sampler_ab", {"base": args.base, "isa": sampler_isa(), "views": args.views, "reps": args.reps,
                                "records": records}, table)


if __name__ == "__main__":
    main()

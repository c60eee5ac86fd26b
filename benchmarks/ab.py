"""Today's tree against an earlier commit's, in one run (A/B): the CPU sampler alone, or a stage-1 step by phase.

``--base`` is any revision git understands, usually relative to HEAD (``HEAD~1``: what the last commit changed;
``HEAD~20``); the record names the commit it resolved to. The base's sources come from ``git archive`` into the
op cache, one folder per commit, built once.

* ``sampler`` — the base's CPU extension (its ``ops/csrc``, its flags) loaded as a second module beside today's;
  both sample the same projected surfels of the same views with the same settings and seeds, calls interleaved
  (A, B, A, B, ...), on 1 and on 2 threads. Reported per scene and thread count: median wall and process CPU
  milliseconds per view, the ratio base / today, and the exact kernel evaluations per covered pixel of each. The
  draws of the two builds may differ (a new random number scheme), so samples are compared in law by the tests,
  not here. Scenes: ``default`` — the main job's stage-1 surfels (``--default-ply``), 64²; ``lego`` — the fitted
  surfels of configs/lego_splat_only.yaml (``--lego-ply``), 200²; each with its config's render settings.
* ``step`` — the base tree (its packages linked as ``nsplat.ops`` / ``nsplat.models``, its op built into its own
  cache folder) runs its own ``benchmarks/step_phases.py`` in a child process on the same fitted surfels, config
  and thread count; then today's :mod:`benchmarks.step_phases` runs the same way, rounds alternating. Each
  phase's figure is the median over rounds of its mean per step; reported: milliseconds per phase of each tree
  and the ratio base / today per phase, for the sampler, the rest of the step and the step.

    python train.py --run runs/default                                                       # ~2 min
    python train.py --config configs/lego_splat_only.yaml --run runs/lego_splat_only          # ~15 min
    python -m benchmarks.ab sampler --base HEAD~1        # ~3 min (+ about a minute to build the base once)
    python -m benchmarks.ab sampler --base HEAD~1 --scenes default --threads 1 --reps 3
    python -m benchmarks.ab step --base HEAD~1           # ~4 min (+ about two minutes to build the base once)

Writes ``benchmarks/results/sampler_ab.json`` or ``step_ab.json`` (``--name`` picks another file name).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
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
from nsplat.tasks.neural.starts import geometry_scene_config

SCENES = {"default": ("configs/default.yaml", "runs/default/geometry.ply"),
          "lego": ("configs/lego_splat_only.yaml", "runs/lego_splat_only/geometry.ply")}
#: The phase of a step that is the sampler (``benchmarks.step_phases``).
SAMPLER = "sampler"


def resolve(rev: str) -> str:
    """The short commit id of revision ``rev`` (``HEAD~1``, a tag, an id)."""
    try:
        return subprocess.run(["git", "rev-parse", "--short", f"{rev}^{{commit}}"], cwd=REPO, capture_output=True,
                              text=True, check=True).stdout.strip()
    except subprocess.CalledProcessError as e:
        raise SystemExit(f"--base: git does not know {rev!r}: {e.stderr.strip()}") from None


def unpack(commit: str, dest: Path, paths: list[str]) -> None:
    """``git archive`` of ``paths`` (all of the tree when empty) at ``commit``, extracted into ``dest``."""
    with tempfile.TemporaryDirectory() as tmp:
        tar = Path(tmp) / "tree.tar"
        subprocess.run(["git", "archive", "-o", str(tar), commit, *paths], cwd=REPO, check=True)
        dest.mkdir(parents=True, exist_ok=True)
        with tarfile.open(tar) as t:
            t.extractall(dest, filter="data")


# ---- sampler: the two extensions in one process


def base_module(commit: str) -> ModuleType:
    """The CPU extension of ``commit`` (its ``ops/csrc``, its flags), built once into its own cache folder."""
    from torch.utils.cpp_extension import load

    out = build_dir(f"ab-{commit}")
    src = out / "csrc"
    if not (src / "cpu" / "splat_cpu.cpp").is_file():
        with tempfile.TemporaryDirectory() as tmp:
            unpack(commit, Path(tmp), ["ops/csrc"])
            (Path(tmp) / "ops" / "csrc").rename(src)
    sources = [str(p) for p in sorted((src / "cpu").glob("*.cpp"))]
    return load(name=f"nsplat_cpu_{commit}", sources=sources, extra_include_paths=[str(src)],
                extra_cflags=["-O3", "-fopenmp", f"-std={cxx_standard()}"], extra_ldflags=["-fopenmp"],
                build_directory=str(out), verbose=False)


def scene_inputs(name: str, ply: Path, views: int) -> tuple[list[list[torch.Tensor]], int, int, dict]:
    """The native sampler's inputs for each of the first ``views`` training views: the projected surfels
    (``means2d [N,2]``, ``conics [N,3]``, ``amps [N]``, ``sigma2 [N]``, ``normals_cam [N,3]``, ``plane_offsets
    [N]``, ``depths [N]``) and ``K [1,3,3]``; the image width and height; the render settings."""
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
    return inputs, train.width, train.height, settings


def sample_call(mod: ModuleType, args: list, width: int, height: int, s: dict, seed: int) -> list:
    """One native ``sample`` call: per-camera random streams, or, for a base from before the tile-lane sampler,
    its single seed for all cameras."""
    tail = (width, height, s["samples"], s["eps"])
    rest = (s["hermite_order"], s["hermite_tol"], 0, False)
    try:
        return mod.sample(*args, camera_streams(torch.tensor(seed), 1), *tail, *rest)
    except TypeError:
        return mod.sample(*args, *tail, seed, *rest)


def measure(modules: dict[str, ModuleType], inputs: list, width: int, height: int, s: dict, reps: int) -> dict:
    """Interleaved calls of each module's ``sample`` on every view: per module, per-view wall/CPU ms (medians over
    reps) and evaluations per covered pixel."""
    for mod in modules.values():  # warm-up (thread pools, caches)
        sample_call(mod, inputs[0], width, height, s, 0)
    wall: dict[str, list[float]] = {n: [] for n in modules}
    cpu_t: dict[str, list[float]] = {n: [] for n in modules}
    work: dict[str, list[float]] = {n: [] for n in modules}
    for rep in range(reps):
        for name, mod in modules.items():
            w0, c0 = time.perf_counter(), time.process_time()
            outs = [sample_call(mod, args, width, height, s, rep + 1) for args in inputs]
            wall[name].append((time.perf_counter() - w0) / len(inputs))
            cpu_t[name].append((time.process_time() - c0) / len(inputs))
            work[name] += [float(o[3][o[2] > 0].double().mean()) for o in outs]
    return {n: {"wall_ms": 1e3 * statistics.median(wall[n]), "cpu_ms": 1e3 * statistics.median(cpu_t[n]),
                "evals_per_covered_px": statistics.mean(work[n])} for n in modules}


def sampler_ab(args: argparse.Namespace, commit: str, ap: argparse.ArgumentParser) -> None:
    plies = {"default": args.default_ply, "lego": args.lego_ply}
    for name in args.scenes:
        if not plies[name].is_file():
            ap.error(f"--{name}-ply: {plies[name]} not found; train it first: python train.py --config "
                     f"{SCENES[name][0]} --run {plies[name].parent}")
    modules = {"base": base_module(commit), "today": backend(torch.device("cpu"))}
    rows, records = [], []
    for name in args.scenes:
        inputs, width, height, settings = scene_inputs(name, plies[name], args.views)
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
    table = markdown(["scene", "N", "res", "threads", f"base {commit} ms (wall / CPU)", "today ms (wall / CPU)",
                      "speed-up (wall / CPU)", "evals per covered px (base / today)"], rows)
    write_result(args.name or "sampler_ab", {"base": commit, "base_rev": args.base, "isa": sampler_isa(),
                                             "views": args.views, "reps": args.reps, "records": records}, table)


# ---- step: each tree's step_phases in its own process


def base_tree(commit: str) -> Path:
    """The tree of ``commit``, with ``nsplat/ops`` and ``nsplat/models`` linked to its top-level ``ops/`` and
    ``models/`` so that it imports from a plain ``PYTHONPATH``."""
    tree = build_dir(f"ab-tree-{commit}") / "tree"
    if not (tree / "benchmarks" / "step_phases.py").is_file():
        unpack(commit, tree, [])
        for pkg in ("ops", "models"):
            link = tree / "nsplat" / pkg
            if not link.exists():
                link.symlink_to(Path("..") / pkg)
    return tree


def run_phases(tree: Path, ply: str, config: str, steps: int, threads: int) -> dict:
    """Runs ``tree``'s step_phases in a child process; returns its result JSON."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": str(threads)}
    if tree != REPO:  # the base's op builds into its own cache (both builds stay compiled)
        env["NSPLAT_BUILD_DIR"] = str(tree.parent / "op")
    cmd = [sys.executable, "benchmarks/step_phases.py", ply, "--config", config, "--steps", str(steps)]
    subprocess.run(cmd, cwd=tree, env=env, check=True, stdout=subprocess.DEVNULL)
    return json.loads((tree / "benchmarks" / "results" / "step_phases.json").read_text())


def step_ab(args: argparse.Namespace, commit: str, ap: argparse.ArgumentParser) -> None:
    ply = str(Path(args.ply).resolve())
    if not Path(ply).is_file():
        ap.error(f"--ply: {ply} does not exist (train configs/lego_splat_only.yaml first, see the docstring)")
    tree = base_tree(commit)
    runs: dict[str, list[dict]] = {"base": [], "today": []}
    for _ in range(args.rounds):
        runs["base"].append(run_phases(tree, ply, args.config, args.steps, args.threads))
        runs["today"].append(run_phases(REPO, ply, args.config, args.steps, args.threads))
    phases = [row["phase"] for row in runs["today"][0]["rows"]]
    med = {k: {p: statistics.median(next(r["ms"] for r in run["rows"] if r["phase"] == p) for run in v)
               for p in phases} for k, v in runs.items()}
    for k in med:
        med[k]["rest of the step"] = sum(ms for p, ms in med[k].items() if p != SAMPLER)
        med[k]["step"] = med[k]["rest of the step"] + med[k][SAMPLER]
    rows = [[p, f"{med['base'][p]:.1f}", f"{med['today'][p]:.1f}", f"{med['base'][p] / med['today'][p]:.2f}x"]
            for p in med["today"]]
    table = markdown(["phase", f"{commit} ms", "today ms", "base / today"], rows)
    print(f"{ply}: {runs['today'][0]['points']} surfels, {args.threads} threads, {args.steps} steps x {args.rounds} "
          f"rounds (medians)")
    write_result(args.name or "step_ab", {"base": commit, "base_rev": args.base, "ply": ply, "config": args.config,
                                          "points": runs["today"][0]["points"], "steps": args.steps,
                                          "rounds": args.rounds, "threads": args.threads, "ms": med,
                                          "speedup": {p: med["base"][p] / med["today"][p] for p in med["today"]},
                                          "runs": runs}, table)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="what", required=True)
    s = sub.add_parser("sampler", help="the CPU sampler alone, both builds in one process")
    s.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    s.add_argument("--default-ply", type=Path, default=REPO / SCENES["default"][1])
    s.add_argument("--lego-ply", type=Path, default=REPO / SCENES["lego"][1])
    s.add_argument("--threads", nargs="+", type=int, default=[2, 1])
    s.add_argument("--views", type=int, default=4, help="training views sampled per repetition")
    s.add_argument("--reps", type=int, default=5)
    t = sub.add_parser("step", help="a stage-1 step phase by phase, each tree in its own process")
    t.add_argument("--ply", default=str(REPO / "runs" / "lego_splat_only" / "geometry.ply"))
    t.add_argument("--config", default="configs/lego.yaml")
    t.add_argument("--steps", type=int, default=20)
    t.add_argument("--rounds", type=int, default=3)
    t.add_argument("--threads", type=int, default=2)
    for p in (s, t):
        p.add_argument("--base", required=True, help="the earlier revision, e.g. HEAD~1")
        p.add_argument("--name", help="the result's file name in benchmarks/results (no suffix)")
    args = ap.parse_args()
    (sampler_ab if args.what == "sampler" else step_ab)(args, resolve(args.base), ap)


if __name__ == "__main__":
    main()

"""One stage-1 step of today's tree against an earlier commit's, phase by phase (A/B in one run).

The earlier tree (``--base``, default the commit before the tile-lane sampler) is unpacked from ``git archive``
into the op cache (its packages linked as ``nsplat.ops`` / ``nsplat.models``, its op built into its own cache
folder) and runs its own ``benchmarks/step_phases.py`` in a child process on the same fitted surfels, config and
thread count; then today's :mod:`benchmarks.step_phases` runs the same way. Rounds alternate (base, today, base,
today, ...); each phase's figure is the median over rounds of its mean per step. Reported: milliseconds per phase
of each tree, the ratio base / today per phase, for the sampler, for the rest of the step and for the step.

    python train.py --config configs/lego_splat_only.yaml --run runs/lego_splat_only      # the surfels (~15 min)
    python -m benchmarks.step_ab                     # ~4 min (+ about two minutes to build the base once)
    python -m benchmarks.step_ab --rounds 1 --steps 5
    python -m benchmarks.step_ab --base f2a997e --name step_ab-f2a997e    # against another commit, kept beside

Writes ``benchmarks/results/step_ab.json`` (or ``<--name>.json``).
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
from pathlib import Path

from benchmarks.common import REPO, markdown, write_result
from nsplat.ops.build import build_dir

DEFAULT_BASE = "5a3af74"
SAMPLER = "sampler"


def base_tree(rev: str) -> Path:
    """The tree of commit ``rev`` (``git archive``), with ``nsplat/ops`` and ``nsplat/models`` linked to its
    top-level ``ops/`` and ``models/`` so that it imports from a plain ``PYTHONPATH``."""
    out = build_dir(f"ab-tree-{rev}")
    tree = out / "tree"
    if not (tree / "benchmarks" / "step_phases.py").is_file():
        with tempfile.TemporaryDirectory() as tmp:
            tar = Path(tmp) / "tree.tar"
            subprocess.run(["git", "archive", "-o", str(tar), rev], cwd=REPO, check=True)
            tree.mkdir(parents=True, exist_ok=True)
            with tarfile.open(tar) as t:
                t.extractall(tree, filter="data")
        for pkg in ("ops", "models"):
            link = tree / "nsplat" / pkg
            if not link.exists():
                link.symlink_to(Path("..") / pkg)
    return tree


def run_phases(tree: Path, module: bool, ply: str, config: str, steps: int, threads: int) -> dict:
    """Runs ``tree``'s step_phases in a child process; returns its result JSON."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": str(threads)}
    if tree != REPO:  # the base's op builds into its own cache (both builds stay compiled)
        env["NSPLAT_BUILD_DIR"] = str(tree.parent / "op")
    cmd = [sys.executable, *(["-m", "benchmarks.step_phases"] if module else ["benchmarks/step_phases.py"]),
           ply, "--config", config, "--steps", str(steps)]
    subprocess.run(cmd, cwd=tree, env=env, check=True, stdout=subprocess.DEVNULL)
    return json.loads((tree / "benchmarks" / "results" / "step_phases.json").read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", default=DEFAULT_BASE, help="the earlier commit (default %(default)s)")
    ap.add_argument("--ply", default=str(REPO / "runs" / "lego_splat_only" / "geometry.ply"))
    ap.add_argument("--config", default="configs/lego.yaml")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--name", default="step_ab", help="the result's file name in benchmarks/results (no suffix)")
    args = ap.parse_args()
    ply = str(Path(args.ply).resolve())
    if not Path(ply).is_file():
        raise SystemExit(f"--ply: {ply} does not exist (train configs/lego_splat_only.yaml first, see the docstring)")
    tree = base_tree(args.base)
    runs: dict[str, list[dict]] = {"base": [], "today": []}
    for _ in range(args.rounds):
        runs["base"].append(run_phases(tree, False, ply, args.config, args.steps, args.threads))
        runs["today"].append(run_phases(REPO, True, ply, args.config, args.steps, args.threads))
    phases = [row["phase"] for row in runs["today"][0]["rows"]]
    med = {k: {p: statistics.median(next(r["ms"] for r in run["rows"] if r["phase"] == p) for run in v)
               for p in phases} for k, v in runs.items()}
    for k in med:
        med[k]["rest of the step"] = sum(ms for p, ms in med[k].items() if p != SAMPLER)
        med[k]["step"] = med[k]["rest of the step"] + med[k][SAMPLER]
    rows = [[p, f"{med['base'][p]:.1f}", f"{med['today'][p]:.1f}", f"{med['base'][p] / med['today'][p]:.2f}x"]
            for p in med["today"]]
    table = markdown(["phase", f"{args.base} ms", "today ms", "base / today"], rows)
    print(f"{ply}: {runs['today'][0]['points']} surfels, {args.threads} threads, {args.steps} steps x {args.rounds} "
          f"rounds (medians)")
    print(table)
    write_result(args.name, {"base": args.base, "ply": ply, "config": args.config, "points": runs["today"][0]["points"],
                             "steps": args.steps, "rounds": args.rounds, "threads": args.threads,
                             "ms": med, "speedup": {p: med["base"][p] / med["today"][p] for p in med["today"]},
                             "runs": runs}, table)


if __name__ == "__main__":
    sys.exit(main())

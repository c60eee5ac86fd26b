"""What every benchmark shares: where results go, the record of the machine, and "run this config".

* :data:`RESULTS` / :data:`IMAGES` — the results folder (``benchmarks/results/``, JSON) and the figures folder
  (``docs/images/``). ``NSPLAT_BENCH_OUT=DIR`` sends both under ``DIR`` (the CI smoke runs: nothing in the
  tree is overwritten).
* :func:`machine` — the commit (and whether the tree had changes), the CPU model and its vector flags, the
  thread count, torch's version and the load average: what every result names.
* :func:`write_result` — one result: the JSON (with :func:`machine` added) and, when given, the Markdown table
  printed on stdout.
* :func:`run_config` — ``python train.py --config CONFIG --run-dir DIR OVERRIDES`` in its own process (its own peak
  memory and threads), with wall and CPU seconds and the load average before and after.

Every script runs from the repository root as ``python -m benchmarks.<name>`` (``benchmarks/README.md``).
"""
from __future__ import annotations

import json
import os
import platform
import re
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch

from nsplat.run.engine import write_json

#: The repository root.
REPO = Path(__file__).resolve().parents[1]
_OUT = os.environ.get("NSPLAT_BENCH_OUT")
#: Where results (JSON) go.
RESULTS = Path(_OUT) / "results" if _OUT else REPO / "benchmarks" / "results"
#: Where figures go (a subfolder per topic, as in ``docs/images/``).
IMAGES = Path(_OUT) / "images" if _OUT else REPO / "docs" / "images"
#: The CPU flags worth naming beside a timing (vector units the op's build may use, native bfloat16 for the networks).
CPU_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512dq", "avx512bw", "avx512vl", "avx512_vnni",
             "avx512_bf16",
             "amx_tile", "amx_bf16", "neon", "asimd", "sve")


def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""


def cpu() -> dict[str, Any]:
    """``{model, family, flags, cores}``: the CPU's model name, its ``vendor family/model/stepping`` (which names
    the generation where a virtual machine masks the model name, e.g. ``AuthenticAMD 25/17/1``: Zen 4) and the
    :data:`CPU_FLAGS` it has (from ``/proc/cpuinfo``; ``platform.processor()`` elsewhere)."""
    model, flags = platform.processor() or platform.machine(), set()
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        text = ""
    if m := re.search(r"^model name\s*:\s*(.+)$", text, re.M):
        model = m.group(1).strip()
    ids = [re.search(rf"^{key}\s*:\s*(\S+)", text, re.M) for key in ("vendor_id", "cpu family", "model", "stepping")]
    family = f"{ids[0].group(1)} {'/'.join(m.group(1) for m in ids[1:])}" if all(ids) else None
    if m := re.search(r"^(?:flags|Features)\s*:\s*(.+)$", text, re.M):
        flags = set(m.group(1).split())
    return {"model": model, "family": family, "flags": [f for f in CPU_FLAGS if f in flags], "cores": os.cpu_count()}


def machine() -> dict[str, Any]:
    """The record every result carries: commit, CPU, threads, versions, load average, time."""
    return {"commit": _git("rev-parse", "HEAD") or "unknown", "dirty": bool(_git("status", "--porcelain")),
            "cpu": cpu(), "threads": torch.get_num_threads(), "torch": torch.__version__,
            "python": platform.python_version(), "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available()
            else None, "load_avg": list(os.getloadavg()), "date": time.strftime("%Y-%m-%d %H:%M:%S %z")}


def write_result(name: str, data: dict[str, Any], table: str | None = None) -> Path:
    """Write ``RESULTS/<name>.json`` (``data`` with ``machine``: :func:`machine`) atomically and print ``table``
    (Markdown) on stdout; returns the JSON's path."""
    path = RESULTS / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, {**data, "machine": machine()})
    if table:
        print(table)
    print(f"wrote {path}", file=sys.stderr)
    return path


def read_result(name: str) -> dict[str, Any] | None:
    """``RESULTS/<name>.json`` if it exists (to merge new runs into an earlier record), else ``None``."""
    path = RESULTS / f"{name}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def markdown(header: list[str], rows: list[list[Any]]) -> str:
    """A Markdown table of ``rows`` under ``header`` (cells formatted with ``str``)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def run_config(config: str | Path, run_dir: Path, overrides: list[str] = (), *, env: dict[str, str] | None = None,
               command: list[str] | None = None, log: Path | None = None) -> dict[str, Any]:
    """Train ``config`` (a path, or the name of a shipped config) with ``overrides`` into ``run_dir`` as its own
    process: ``python train.py --config CONFIG --run-dir RUN_DIR OVERRIDES`` (``command`` replaces
    ``[python, train.py]``, e.g. with torchrun; ``env`` is added to the environment; stdout and stderr go to
    ``log``, default ``RUN_DIR.log``). A folder holding a finished run is overwritten.

    Returns ``{returncode, wall_s, cpu_s, load_before, load_after, log}``; raises ``RuntimeError`` when the run
    fails (naming its log).
    """
    run_dir = Path(run_dir)
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    log = log or run_dir.with_suffix(".log")
    argv = [*(command or [sys.executable, str(REPO / "train.py")]), "--config", str(config), "--run-dir",
            str(run_dir), "--overwrite", *overrides]
    load_before = list(os.getloadavg())
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.run(argv, cwd=REPO, stdout=fh, stderr=subprocess.STDOUT, env={**os.environ, **(env or {})})
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed ({proc.returncode}); see {log}")
    return {"returncode": proc.returncode, "wall_s": wall,
            "cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
            "load_before": load_before, "load_after": list(os.getloadavg()), "log": str(log)}


def _read_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def val_curve(run: Path) -> list[tuple[float, float]]:
    """``(training seconds, val PSNR)`` of a run folder's stage 1 (``geometry_history.json``), then stage 2
    (``history.json``, offset by stage 1's time when the run finished it); the seconds exclude validation."""
    pts = [(h["elapsed_s"], h["val_psnr"]) for h in (_read_json(run / "geometry_history.json") or {}).get("history",
                                                                                                          [])]
    offset = (_read_json(run / "timing.json") or {}).get("geometry_s", 0.0)
    pts += [(offset + h["elapsed_s"], h["val_psnr"]) for h in (_read_json(run / "history.json") or {}).get("history",
                                                                                                           [])]
    return pts


def run_curve(run: Path) -> dict:
    """``{curve: [[s, val PSNR], ...], stage1_points, finished, stage1_test_psnr, test_psnr}`` of the run folder
    ``run``, finished or stopped (a time limit keeps the validations it reached)."""
    if not run.is_dir():
        raise FileNotFoundError(f"run: no run folder at {run}")
    pts = val_curve(run)
    stage1 = len((_read_json(run / "geometry_history.json") or {}).get("history", []))
    geometry, metrics = _read_json(run / "eval_geometry.json") or {}, _read_json(run / "eval_test" / "metrics.json")
    return {"curve": [list(p) for p in pts], "stage1_points": stage1, "finished": (run / "timing.json").is_file(),
            "stage1_test_psnr": geometry.get("test", {}).get("psnr", {}).get("mean"),
            "test_psnr": metrics["psnr"]["mean"] if metrics else None}


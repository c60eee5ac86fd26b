"""Cost of the live training view (``viewer=true``) on a tiny neural run. Not run in CI.

    python -m benchmarks.viewer_live_cost [--steps 40] [--repeats 1]

Trains the same tiny config (procedural scene at 32 px, 8 training views, 2 stage-1 epochs, ``--steps``
stage-2 steps) three ways, each as its own ``train.py`` process: without the viewer; with
``viewer=true`` and no browser; with ``viewer=true viewer.refresh_every=1`` and a headless Chromium
page connected for the whole run (the viewer then renders as often as its budget allows). Reports the
wall time and the CPU time (user + system) of the training process — Chromium's own CPU is not
counted in the latter, but competes for the cores in the former — and the viewer's own account
("N renders, X s in the viewer"). Writes ``benchmarks/results/viewer_live_cost.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO, write_result
from nsplat.viewer.server import free_port

TINY = """task: neural
seed: 0
data:
  procedural: {{seed: 1, resolution: 32, views: [8, 2, 2], objects: 2, cache_dir: {cache}}}
geometry: {{grid: 32, optim: {{epochs: 2, batch: 4, reposition: {{enabled: false}}}}}}
render: {{samples: 16}}
neural: {{steps: {steps}, batch: 2, features: 4, unet: {{depth: 2, width: 8}}, gan: {{width: 8, layers: 2}}}}
log: {{every: 5, images: 0, checkpoint: 1000, validate: 0, progress: false}}
eval: {{images: false}}
"""


def _wait_port(port: int, proc: subprocess.Popen, timeout: float = 120.0) -> bool:
    t_end = time.time() + timeout
    while time.time() < t_end and proc.poll() is None:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return True
        time.sleep(0.2)
    return False


def one(cfg: Path, run: Path, extra: list[str], browser: bool) -> dict:
    """Train once; wall and CPU seconds of the training process and the viewer's log line."""
    shutil.rmtree(run, ignore_errors=True)
    port = free_port()
    args = [sys.executable, str(REPO / "train.py"), "--config", str(cfg), "--run", str(run), *extra]
    if extra:
        args.append(f"viewer.port={port}")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=os.environ.copy())
    chrome = None
    profile = tempfile.mkdtemp(prefix="nsplat-chromium-")
    if browser and _wait_port(port, proc):
        chrome = subprocess.Popen([shutil.which("chromium"), "--headless=new", "--no-sandbox", "--use-angle=swiftshader",
                                   "--enable-unsafe-swiftshader", f"--user-data-dir={profile}",
                                   "--window-size=800,600", f"http://127.0.0.1:{port}/"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    out, _ = proc.communicate()
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)  # chromium is still running: not counted yet
    if chrome is not None:
        chrome.terminate()
        chrome.wait(timeout=20)
    shutil.rmtree(profile, ignore_errors=True)
    if proc.returncode != 0:
        raise RuntimeError(f"training failed:\n{out[-3000:]}")
    m = re.search(r"live viewer: (\d+) renders, ([\d.]+) s in the viewer", out)
    return {"wall_s": round(wall, 2), "cpu_s": round(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime, 2),
            "viewer_renders": int(m.group(1)) if m else None, "viewer_s": float(m.group(2)) if m else None}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--repeats", type=int, default=1)
    args = p.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="nsplat-live-cost-"))
    cfg = tmp / "tiny.yaml"
    cfg.write_text(TINY.format(cache=tmp / "cache", steps=args.steps))
    small = ["viewer.resolution=192", "viewer.render.samples=8"]  # a cheap live view
    cases = {"no viewer": ([], False), "viewer=true, no browser": (["viewer=true", *small], False),
             "viewer=true, headless Chromium connected, refresh_every=1": (
                 ["viewer=true", "viewer.refresh_every=1", *small], True)}
    one(cfg, tmp / "warm", [], False)  # generates the scene; warms the file cache
    results = {name: [one(cfg, tmp / "run", extra, browser) for _ in range(args.repeats)]
               for name, (extra, browser) in cases.items()}
    report = {"steps": args.steps, "note": "2-core machine shared with other jobs; wall times are noisy",
              "cases": results}
    write_result("viewer_live_cost", report, json.dumps(report, indent=1))
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

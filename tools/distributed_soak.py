"""Soak of data-parallel runs: the 2-process runs of tests/test_distributed.py repeated many times, counting
every run that does not end as it should (a rank that aborts at exit, a wrong exit status, a hang).

Three kinds of run, each on the tests' tiny procedural scene (``tests.test_distributed._tiny``):

* ``plain`` — ``torchrun --nproc_per_node=2 train.py``: both ranks exit 0 and the run folder holds its
  held-out metrics;
* ``killed`` — 2 ranks started with torchrun's environment; rank 1 is killed after the first stage-2 checkpoint,
  rank 0 must stop with the distributed error (exit 1) within the timeout, then a 2-rank ``--resume`` exits 0
  on both ranks;
* ``resumed`` — a 1-process run's step-10 checkpoint resumed with 2 processes exits 0 on both ranks.

A failure is recorded with its exit statuses and the tail of each rank's stderr (``terminate called`` /
SIGABRT is the abort at exit this soak guards against). Writes ``benchmarks/results/distributed_soak.json``.

    python -m tools.distributed_soak --repeats 30
"""
from __future__ import annotations

import argparse
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from benchmarks.common import REPO, markdown, write_result
from tests.test_distributed import RUN_TIMEOUT_S, TIMEOUT_S, _env, _ranks, _tiny, _torchrun

KINDS = ("plain", "killed", "resumed")


def _abort(err: str) -> bool:
    return "terminate called" in err or "SIGABRT" in err or "Signal 6" in err


def _ok(results: list[tuple[int, str]]) -> tuple[bool, str]:
    """Whether every rank exited 0, and else why."""
    if all(code == 0 for code, _ in results):
        return True, ""
    bad = [(r, code, err) for r, (code, err) in enumerate(results) if code != 0]
    return False, "; ".join(f"rank {r} exit {code}{' (abort at exit)' if _abort(err) else ''}: "
                            f"{' '.join(err.split()[-60:])}" for r, code, err in bad)


def plain(config: Path, run: Path) -> tuple[bool, str]:
    res = _torchrun("--config", str(config), "--run-dir", str(run))
    if res.returncode != 0:
        return False, f"torchrun exit {res.returncode}{' (abort at exit)' if _abort(res.stderr) else ''}: " \
                      f"{' '.join(res.stderr.split()[-60:])}"
    if not (run / "eval_test" / "metrics.json").is_file():
        return False, "no eval_test/metrics.json"
    return True, ""


def killed(config: Path, run: Path) -> tuple[bool, str]:
    job = _ranks("--config", str(config), "--run", str(run), "--dist-timeout", str(TIMEOUT_S))
    latest = run / "checkpoints" / "latest"
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while not latest.is_file() and time.monotonic() < deadline and all(p.poll() is None for p in job.procs):
        time.sleep(0.02)
    if not latest.is_file():
        for p in job.procs:
            p.kill()
        tails = [" ".join(err.split()[-40:]) for _, err in job.finish()]
        return False, f"no stage-2 checkpoint appeared: {tails}"
    job.procs[1].send_signal(signal.SIGKILL)
    (code, err), _ = job.finish()
    if code != 1 or "another rank died" not in err:
        return False, f"rank 0 after the kill: exit {code}: {' '.join(err.split()[-60:])}"
    return _ok(_ranks("--run", str(run), "--resume").finish())


def resumed(one: Path, run: Path) -> tuple[bool, str]:
    shutil.copytree(one, run)
    (run / "checkpoints" / "ckpt-00000012.pt").unlink()
    (run / "checkpoints" / "latest").write_text("ckpt-00000010.pt")
    (run / "finished.json").unlink()
    return _ok(_ranks("--run", str(run), "--resume").finish())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=30, help="runs of each kind (default 30)")
    ap.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS))
    args = ap.parse_args()
    if args.repeats < 1:
        ap.error(f"--repeats: expected >= 1, got {args.repeats}")
    root = Path(tempfile.mkdtemp(prefix="nsplat-soak-"))
    try:
        config = root / "tiny.yaml"
        config.write_text(yaml.safe_dump(_tiny(root / "scenes")))
        one = root / "one"
        if "resumed" in args.kinds:
            res = subprocess.run([sys.executable, str(REPO / "train.py"), "--config", str(config), "--run", str(one)],
                                 env=_env(), cwd=REPO, capture_output=True, text=True, timeout=RUN_TIMEOUT_S)
            if res.returncode != 0:
                raise SystemExit(f"the 1-process reference run failed: {res.stderr[-2000:]}")
        runs, t0 = [], time.perf_counter()
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        for i in range(args.repeats):
            for kind in args.kinds:
                run = root / f"{kind}-{i}"
                t = time.perf_counter()
                ok, why = {"plain": lambda: plain(config, run), "killed": lambda: killed(config, run),
                           "resumed": lambda: resumed(one, run)}[kind]()
                runs.append({"kind": kind, "repeat": i, "ok": ok, "why": why, "wall_s": time.perf_counter() - t})
                print(f"{kind} {i}: {'ok' if ok else 'FAILED ' + why}", file=sys.stderr, flush=True)
                shutil.rmtree(run, ignore_errors=True)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    rows = [[k, sum(r["kind"] == k for r in runs), sum(r["kind"] == k and not r["ok"] for r in runs),
             f"{sum(r['wall_s'] for r in runs if r['kind'] == k) / max(1, sum(r['kind'] == k for r in runs)):.1f}"]
            for k in args.kinds]
    write_result("distributed_soak", {
        "repeats": args.repeats, "runs": len(runs), "failures": sum(not r["ok"] for r in runs),
        "wall_s": time.perf_counter() - t0,
        "cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
        "per_kind": {kind: {"runs": n, "failures": failed} for kind, n, failed, _ in rows},
        "failed": [r for r in runs if not r["ok"]], "all": runs},
        markdown(["kind", "runs", "failures", "mean wall s"], rows))


if __name__ == "__main__":
    main()

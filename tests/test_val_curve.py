"""tools.val_curve: a run folder's val PSNR against training time, finished or stopped by a time limit."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.common import run_curve


def _write(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def test_stopped_run_keeps_its_stage1_points(tmp_path: Path) -> None:
    _write(tmp_path / "geometry_history.json", {"history": [{"step": 40, "elapsed_s": 2.0, "val_psnr": 18.5},
                                                            {"step": 80, "elapsed_s": 3.5, "val_psnr": 20.0}]})
    rec = run_curve(tmp_path)
    assert rec["curve"] == [[2.0, 18.5], [3.5, 20.0]]
    assert rec["stage1_points"] == 2 and not rec["finished"]
    assert rec["test_psnr"] is None and rec["stage1_test_psnr"] is None


def test_finished_run_offsets_stage2_by_stage1_time(tmp_path: Path) -> None:
    _write(tmp_path / "geometry_history.json", {"history": [{"step": 40, "elapsed_s": 2.0, "val_psnr": 18.5}]})
    _write(tmp_path / "history.json", {"history": [{"step": 50, "elapsed_s": 1.5, "val_psnr": 25.0}]})
    _write(tmp_path / "timing.json", {"geometry_s": 10.0, "train_total_s": 12.0})
    _write(tmp_path / "eval_geometry.json", {"test": {"psnr": {"mean": 21.0}}})
    _write(tmp_path / "eval_test" / "metrics.json", {"psnr": {"mean": 26.0}})
    rec = run_curve(tmp_path)
    assert rec["curve"] == [[2.0, 18.5], [11.5, 25.0]]
    assert rec["stage1_points"] == 1 and rec["finished"]
    assert rec["stage1_test_psnr"] == 21.0 and rec["test_psnr"] == 26.0


def test_missing_run_folder_is_named(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="no run folder"):
        run_curve(tmp_path / "absent")

"""The one-line note of a capture whose stage 1 fits the training photos far better than it predicts the held-out
ones (issue 70, part 5): :func:`nsplat.tasks.neural.diagnosis.gap_message` and the explicit ``view_fill`` start."""
from __future__ import annotations

import pytest

from nsplat.config import ConfigError, load_config
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.diagnosis import GAP_DB, gap_message


def test_the_gap_note_is_one_line_with_the_figures_and_a_cause():
    cfg = load_config(Config, {"task": "neural", "data": {"source": "colmap", "root": "somewhere"}})
    text = gap_message(cfg, 31.5, 19.25, 12.25)
    assert "\n" not in text
    assert text.startswith("train 31.50 dB, val 19.25 dB (12.2 dB apart) after stage 1")
    assert "few training photos see" in text and "docs/capture.md" in text
    assert GAP_DB > 0


def test_view_fill_is_a_start_one_can_name():
    cfg = load_config(Config, {"task": "neural", "geometry": {"init": "view_fill"}})
    assert cfg.geometry.init == "view_fill"
    with pytest.raises(ConfigError, match="init"):
        load_config(Config, {"task": "neural", "geometry": {"init": "triangulate"}})

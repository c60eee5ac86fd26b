"""The point-only baseline (issue 28): view-dependent colour by spherical harmonics (``nsplat.render.sh``
``view_colour``), stage 1 alone as a model (``neural.steps: 0``), and stage 1's validation curve."""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch
import yaml

from nsplat.cli import main
from nsplat.config import ConfigError, load_config, read_yaml
from nsplat.evaluation.protocol import read_per_view_csv
from nsplat.gaussians.export import read_ply
from nsplat.render.sh import sh_view_basis, view_channels, view_colour
from nsplat.tasks.neural.config import Config
from nsplat.viewer.runs import load_run
from tests.test_neural import _tiny

REPO = Path(__file__).resolve().parents[1]


def _sphere(n: int) -> torch.Tensor:
    """``n`` nearly uniform unit directions (Fibonacci lattice), float64."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    r = (1 - z * z).sqrt()
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def test_view_basis_is_orthonormal_up_to_degree_3():
    d = _sphere(100_000)
    B = sh_view_basis(d, 3)
    assert B.shape == (100_000, 15)
    gram = 4 * math.pi * (B.T @ B) / d.shape[0]  # ∫ Y_i Y_j dω by the lattice rule
    assert float((gram - torch.eye(15, dtype=torch.float64)).abs().max()) < 1e-5
    # each band is also orthogonal to the constant: ∫ Y_lm dω = 0
    assert float((B.mean(0)).abs().max()) < 1e-5
    # lower degrees are prefixes of the higher ones
    assert torch.equal(sh_view_basis(d, 2), B[:, :8]) and torch.equal(sh_view_basis(d, 1), B[:, :3])


def test_view_colour_is_the_mean_colour_plus_a_view_term():
    g = torch.Generator().manual_seed(0)
    N = 50
    means = torch.randn(N, 3, generator=g, dtype=torch.float64)
    feats = torch.zeros(N, view_channels(3), dtype=torch.float64)
    feats[:, :3] = torch.rand(N, 3, generator=g, dtype=torch.float64)
    V = torch.eye(4, dtype=torch.float64)
    V[:3, 3] = torch.tensor([0.0, 0.0, 4.0])
    # no higher coefficients: the colour is the first three channels, whatever the camera
    assert torch.equal(view_colour(feats, means, V), feats[:, :3])
    # one band-1 coefficient: colour changes with the direction from the camera centre (0, 0, -4)
    feats[:, 3 + 1 * 3: 3 + 2 * 3] = 0.1  # coefficient of Y_10 (z) for R, G and B
    d = torch.nn.functional.normalize(means - torch.tensor([0.0, 0.0, -4.0], dtype=torch.float64), dim=-1)
    want = (feats[:, :3] + 0.1 * math.sqrt(3 / (4 * math.pi)) * d[:, 2:3]).clamp_min(0)
    assert torch.allclose(view_colour(feats, means, V), want, atol=1e-12)
    with pytest.raises(ValueError, match="features"):
        view_colour(feats[:, :10], means, V)


def test_sh_degree_must_match_the_shading(tmp_path):
    with pytest.raises(ConfigError, match="geometry.sh_degree"):
        load_config(Config, _tiny(tmp_path, steps=0) | {"geometry": {"sh_degree": 2}})
    with pytest.raises(ConfigError, match="geometry.sh_degree"):
        load_config(Config, _tiny(tmp_path) | {"geometry": {"optim": {"shading": "sh"}, "sh_degree": 4}})
    cfg = load_config(Config, _tiny(tmp_path) | {"geometry": {"optim": {"shading": "sh"}, "sh_degree": 3}})
    assert cfg.geometry.channels() == 48


def test_point_only_sh_run_trains_evaluates_and_records_its_curve(tmp_path):
    raw = _tiny(tmp_path / "cache", steps=0)
    raw["geometry"] = {"grid": 24, "sh_degree": 2, "log": {"validate": 2},
                       "optim": {"epochs": 2, "batch": 3, "reposition": {"enabled": False}, "shading": "sh"}}
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(raw))
    run = tmp_path / "run"
    assert main(["--config", str(tmp_path / "c.yaml"), "--run", str(run)]) == 0
    geo = json.loads((run / "eval_geometry.json").read_text())
    assert set(geo) >= {"points", "val", "test"} and math.isfinite(geo["test"]["psnr"]["mean"])
    history = json.loads((run / "geometry_history.json").read_text())["history"]
    assert [h["step"] for h in history] == [2, 4]  # 2 epochs of 2 steps (6 views, batch 3)
    assert history[0]["elapsed_s"] < history[1]["elapsed_s"]
    timing = json.loads((run / "timing.json").read_text())
    assert timing["neural_steps_s"] == 0.0 and timing["train_total_s"] == timing["geometry_s"]
    assert not (run / "checkpoints").exists()  # no stage 2
    # the held-out metrics are stage 1's, written as a stage-2 run writes them (the same renders)
    metrics = json.loads((run / "eval_test" / "metrics.json").read_text())
    assert metrics["protocol"] == "standard" and metrics["psnr"] == geo["test"]["psnr"]
    rows = read_per_view_csv(run / "eval_test" / "per_view.csv")
    assert len(rows) == 2 and (run / "eval_test" / "sheet.png").is_file()
    # the stage-1 PLY holds the SH coefficients (3·(2+1)² = 27 channels), the first three the mean colour
    header = (run / "geometry.ply").read_bytes()[:4000]
    assert b"property float f_26" in header and b"property float f_27" not in header


def test_after_training_commands_take_a_point_only_run(tmp_path, capsys):
    """``eval``, ``render``, ``view``'s model and ``export`` of a run without stage 2 use its stage-1 surfels."""
    raw = _tiny(tmp_path / "cache", steps=0)
    raw["geometry"]["optim"]["shading"] = "sh"
    raw["geometry"]["sh_degree"] = 1
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(raw))
    run = tmp_path / "run"
    assert main(["--config", str(tmp_path / "c.yaml"), "--run", str(run)]) == 0
    geo = json.loads((run / "eval_geometry.json").read_text())
    assert main(["eval", "--run", str(run)]) == 0
    standard = json.loads((run / "eval_test" / "metrics.json").read_text())
    assert standard["psnr"] == geo["test"]["psnr"]  # `eval` renders what the run's own evaluation rendered
    assert main(["eval", "--run", str(run), "eval.protocol=nsplat"]) == 0
    plain = json.loads((run / "eval_test" / "metrics.json").read_text())
    assert plain["protocol"] == "nsplat" and plain["ssim"] != standard["ssim"]
    assert "held-out test (2 views, 24x24, nsplat protocol): PSNR" in capsys.readouterr().out
    assert main(["render", "--run", str(run), "--path", "test", "--outputs", "rgb,depth"]) == 0
    assert (run / "test.mp4").is_file() and (run / "test_depth.mp4").is_file()
    model = load_run(run)
    assert model.shader is None and model.sh_degree == 1 and model.cameras is not None
    assert model.num_points == geo["points"]
    assert main(["export", "--run", str(run), "--format", "ply"]) == 0
    assert read_ply(run / "export" / "surfels.ply")["means"].shape == (geo["points"], 3)


def test_shipped_splat_only_config_loads():
    cfg = load_config(Config, read_yaml(REPO / "configs" / "splat_only.yaml"))
    assert cfg.neural.steps == 0 and cfg.geometry.optim.shading == "sh" and cfg.geometry.sh_degree >= 1


def test_lego_point_only_config_is_lego_stage_one_on_half_the_schedule():
    """configs/lego_splat_only.yaml: configs/lego.yaml's stage 1 (data, render and surfel settings) on half of its
    schedule (72 of 144 epochs, the annealing tail 1/6 of them) and no U-Net: the 12- and 30-minute recipes of the
    time-to-quality front (docs/results.md)."""
    point = load_config(Config, read_yaml(REPO / "configs" / "lego_splat_only.yaml"))
    lego = load_config(Config, read_yaml(REPO / "configs" / "lego.yaml"))
    assert point.neural.steps == 0 and lego.neural.steps > 0
    assert point.data == lego.data and point.render == lego.render
    po, lo = point.geometry.optim, lego.geometry.optim
    assert (2 * po.epochs, 2 * po.anneal_epochs) == (lo.epochs, lo.anneal_epochs) == (144, 24)
    po_as_lo = dataclasses.replace(po, epochs=lo.epochs, anneal_epochs=lo.anneal_epochs)
    assert dataclasses.replace(point.geometry, optim=po_as_lo) == lego.geometry
    # stage 2 alone on fitted surfels (what the time-to-quality benchmark's "s1-…+s2-…" rows run) loads too
    again = load_config(Config, read_yaml(REPO / "configs" / "lego.yaml"),
                        ["geometry.init=ply", "geometry.ply=fitted.ply", "geometry.optim.epochs=0"])
    assert again.geometry.optim.epochs == 0 and again.geometry.optim.anneal_epochs == lego.geometry.optim.anneal_epochs


def test_lego_400_config_is_lego_at_full_resolution_on_an_hour():
    """configs/lego_400.yaml: configs/lego.yaml (its views, hull, surfels, U-Net) at the photos' native 400², with
    stage 1 on 3/4 of its schedule (108 epochs, the annealing tail 1/6 of them: a 400² epoch costs about 2.4
    200² ones): the hour-long recipe of the 400² time-to-quality curve (docs/results.md)."""
    big = load_config(Config, read_yaml(REPO / "configs" / "lego_400.yaml"))
    lego = load_config(Config, read_yaml(REPO / "configs" / "lego.yaml"))
    assert (big.data.resolution, lego.data.resolution) == (400, 200)
    assert dataclasses.replace(big.data, resolution=200) == lego.data
    bo, lo = big.geometry.optim, lego.geometry.optim
    assert (4 * bo.epochs, 6 * bo.anneal_epochs) == (3 * lo.epochs, bo.epochs) == (432, 108)
    bo_as_lo = dataclasses.replace(bo, epochs=lo.epochs, anneal_epochs=lo.anneal_epochs)
    assert dataclasses.replace(big.geometry, optim=bo_as_lo) == lego.geometry
    assert big.neural == lego.neural and big.render == lego.render


def test_random_start_draws_max_points_in_the_box(tmp_path):
    """``geometry.init: random`` draws ``max_points`` points in ``geometry.bbox`` instead of the hull's."""
    from nsplat.tasks.neural.data import load_views
    from nsplat.tasks.neural.starts import initial_geometry

    def start(**geometry) -> torch.Tensor:
        raw = _tiny(tmp_path / "cache")
        raw["geometry"] = {"grid": 24, **geometry}
        cfg = load_config(Config, raw)
        return initial_geometry(cfg, load_views(cfg, "train", torch.device("cpu")), seed=0).means.detach()

    hull = start()
    assert hull.shape[0] != 300
    rand = start(init="random", max_points=300, bbox=[-1.0, -0.5, -0.2, 1.0, 0.5, 0.2])
    assert rand.shape == (300, 3)
    assert bool((rand.min(0).values >= torch.tensor([-1.0, -0.5, -0.2])).all())
    assert bool((rand.max(0).values <= torch.tensor([1.0, 0.5, 0.2])).all())

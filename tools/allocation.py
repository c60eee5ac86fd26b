"""What a config allocates and learns ("model only what a scene requires").

:func:`build_config` builds a config's model(s) exactly as its task does, without data loading or
training (point clouds and frames are replaced by placeholders of :data:`N_PLACEHOLDER` points and the
config's camera count); :func:`inventory` lists every parameter and buffer with its shape and whether it
is learned. ``python -m tools.allocation_table`` writes the table of the shipped configs
(``docs/model_allocation.md``); ``tests/test_allocation.py`` checks it.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable

import torch
from torch import nn

from nsplat import fitting
from nsplat.config import load_config, read_yaml
from nsplat.data.views import PosedViews
from nsplat.scene import SceneConfig, SurfelScene
from nsplat.tasks import get_task, neural, reconstruct, refine
from nsplat.tasks.neural.model import neural_scene_config
from nsplat.tasks.neural.starts import geometry_scene_config

#: Placeholder point count; a tensor dimension equal to it is printed as ``N``.
N_PLACEHOLDER = 1009

Models = dict[str, nn.Module | None]


@dataclasses.dataclass
class Entry:
    """One allocated tensor: ``module.name`` of shape ``shape``; ``learned`` when it is a parameter with
    ``requires_grad``; ``persistent`` when it is saved in checkpoints."""

    module: str
    name: str
    shape: tuple[int, ...]
    learned: bool
    persistent: bool = True

    @property
    def per_point(self) -> bool:
        """One of its dimensions is the point count."""
        return N_PLACEHOLDER in self.shape

    def shape_text(self) -> str:
        """The shape with the point count written ``N``, e.g. ``[N, 3]``."""
        return "[" + ", ".join("N" if s == N_PLACEHOLDER else str(s) for s in self.shape) + "]"

    def floats(self) -> int:
        """Floats per point (per-point tensors) or in total (others)."""
        n = 1
        for s in self.shape:
            n *= 1 if s == N_PLACEHOLDER else s
        return n


def inventory(models: Models) -> list[Entry]:
    """Every parameter and buffer (persistent or not) of ``models`` (``None`` entries allocate nothing)."""
    out: list[Entry] = []
    for label, model in models.items():
        if model is None:
            continue
        for mod_name, mod in model.named_modules():
            prefix = f"{label}.{mod_name}" if mod_name else label
            for name, p in mod.named_parameters(recurse=False):
                out.append(Entry(prefix, name, tuple(p.shape), p.requires_grad))
            for name, b in mod.named_buffers(recurse=False):
                out.append(Entry(prefix, name, tuple(b.shape), False, name not in mod._non_persistent_buffers_set))
    return out


# ------------------------------------------------------------------------------------------ builders
def _placeholder_scene(scfg: SceneConfig) -> SurfelScene:
    return SurfelScene(scfg, N_PLACEHOLDER)


def build_demo(cfg: Any) -> tuple[Models, list[str]]:
    """Nothing: the demo renders plain tensors."""
    return {}, [f"renders a fixed procedural scene of {cfg.points} points (plain tensors: means, normals, "
                f"scales, opacities, RGB features); no nn.Module, nothing learned"]


def build_reconstruct(cfg: Any) -> tuple[Models, list[str]]:
    """The fitter's scene."""
    notes = ["Lambert shading with the paper's fixed camera-relative lights (nothing allocated)",
             f"N = init.count or the GT point count ({cfg.data.shape}); render: {cfg.render.renderer}"]
    return reconstruct.build(cfg, "cpu", N_PLACEHOLDER).modules, notes


def build_refine(cfg: Any) -> tuple[Models, list[str]]:
    """The refiner (scene, shading, camera corrections) over placeholder frames (1×1 images)."""
    d = cfg.data
    count = {"room": d.room.frames, "nerf": max(1, d.nerf.limit), "rgbd": max(1, d.rgbd.limit)}[d.source]
    C = cfg.scene.channels
    frames = PosedViews(images=torch.zeros(count, 1, 1, C), viewmats=torch.eye(4).expand(count, 4, 4).clone(),
                        Ks=torch.eye(3).expand(count, 3, 3).clone(), names=[str(i) for i in range(count)],
                        masks=torch.ones(count, 1, 1, dtype=torch.bool))
    modules = refine.build(cfg, _placeholder_scene(cfg.scene), frames).modules
    modules["model"].frames = None  # data, not model state
    notes = [f"cameras: {count} frames (source {cfg.data.source}); shading: {cfg.shading.model}"]
    return modules, notes


def build_neural(cfg: Any) -> tuple[Models, list[str]]:
    """Stage 1's scene, stage 2's renderer and (when enabled) the discriminator; with ``neural.steps: 0`` (the
    point-only model) stage 1's scene alone, as the task builds."""
    stage1 = fitting.build(_placeholder_scene(geometry_scene_config(cfg)), cfg.geometry.optim).modules
    colour = f"SH degree {cfg.geometry.sh_degree} surfels" if cfg.geometry.optim.shading == "sh" else "RGB surfels"
    g = cfg.geometry
    sphere = " plus the background sphere's" if g.background.model == "sphere" else ""
    points = (f"N = the points geometry.init: {g.init} starts from "
              f"(at most geometry.max_points = {g.max_points}){sphere}")
    if cfg.neural.steps == 0:
        return {"stage1_scene": stage1["scene"]}, [f"stage 1 (geometry): {colour}; no stage 2 (neural.steps: 0: "
                                                    "the surfels are the model)", points]
    stage2 = neural.build(cfg, _placeholder_scene(neural_scene_config(cfg))).modules
    disc = stage2.get("disc")
    view = " (+ stage 1's SH coefficients: neural.view_colour)" if cfg.neural.view_colour else ""
    notes = [f"stage 1 (geometry): {colour}; stage 2: {cfg.neural.features} learned features per point{view}, "
             f"U-Net shader, PatchGAN {'on' if disc is not None else 'off (not built)'}", points]
    return {"stage1_scene": stage1["scene"], "stage2": stage2["model"], "discriminator": disc}, notes


BUILDERS: dict[str, Callable[[Any], tuple[Models, list[str]]]] = {
    "demo": build_demo, "reconstruct": build_reconstruct, "refine": build_refine, "neural": build_neural,
}


#: ``data.root`` of a capture config that leaves it to the command line (``configs/colmap.yaml``,
#: ``configs/transforms.yaml``): the inventory allocates with placeholder sizes and reads no data.
CAPTURE_PLACEHOLDER = "<your capture folder>"


def build_config(path: Path, overrides: list[str] | None = None) -> tuple[str, Any, Models, list[str]]:
    """``(task, cfg, models, notes)`` of config file ``path`` with dotted ``key=value`` overrides."""
    raw = read_yaml(path)
    task = get_task(raw["task"])
    overrides = list(overrides or [])
    data = raw.get("data") or {}
    given = any(o.startswith("data.root=") for o in overrides)
    if data.get("source") in ("colmap", "transforms") and not data.get("root") and not given:
        overrides.append(f"data.root={CAPTURE_PLACEHOLDER}")  # given on the command line; never read here
    cfg = load_config(task.Config, raw, overrides)
    if raw["task"] not in BUILDERS:
        raise KeyError(f"{path.name}: no allocation builder for task {raw['task']!r} (add one to BUILDERS)")
    models, notes = BUILDERS[raw["task"]](cfg)
    return raw["task"], cfg, models, notes

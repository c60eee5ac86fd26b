"""What each shipped config allocates and learns ("model only what a scene requires").

For every ``configs/*.yaml`` the script builds the task's model(s) exactly as the task does, without
data loading or training (point clouds and frames are replaced by placeholders of ``N`` points and
the config's camera count), and lists every parameter and buffer with its shape, whether it is
learned, and the floats it costs per point. It writes ``docs/model_allocation.md`` (and prints it).

    python benchmarks/allocation_table.py            # writes docs/model_allocation.md
    python benchmarks/allocation_table.py --check    # exit 1 if the doc is out of date

Shapes use ``N`` for the number of points (built with a placeholder count so that the dimension is
recognisable); everything else is literal.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any, Callable

import torch
from torch import nn

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nsplat.config import load_config, read_yaml  # noqa: E402
from nsplat.scene import SurfelScene  # noqa: E402
from nsplat.tasks import TASKS, get_task  # noqa: E402

#: Placeholder point count; a tensor dimension equal to it is printed as ``N``.
N_PLACEHOLDER = 1009
DOC = ROOT / "docs" / "model_allocation.md"


@dataclasses.dataclass
class Entry:
    """One allocated tensor."""

    module: str
    name: str
    shape: tuple[int, ...]
    learned: bool
    persistent: bool = True

    @property
    def per_point(self) -> bool:
        return N_PLACEHOLDER in self.shape

    def shape_text(self) -> str:
        return "[" + ", ".join("N" if s == N_PLACEHOLDER else str(s) for s in self.shape) + "]"

    def floats(self) -> int:
        """Floats per point (per-point tensors) or in total (others)."""
        n = 1
        for s in self.shape:
            n *= 1 if s == N_PLACEHOLDER else s
        return n


def inventory(models: dict[str, nn.Module | None]) -> list[Entry]:
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
def _placeholder_scene(scfg) -> SurfelScene:
    return SurfelScene(scfg, N_PLACEHOLDER)


def build_demo(cfg) -> tuple[dict[str, nn.Module | None], list[str]]:
    return {}, [f"renders a fixed procedural scene of {cfg.points} points (plain tensors: means, normals, "
                f"scales, opacities, RGB features); no nn.Module, nothing learned"]


def build_reconstruct(cfg) -> tuple[dict[str, nn.Module | None], list[str]]:
    from nsplat.tasks import reconstruct

    notes = ["Lambert shading with the paper's fixed camera-relative lights (nothing allocated)",
             f"N = init.count or the GT point count ({cfg.data.shape}); render: {cfg.render.renderer}"]
    return reconstruct.build(cfg, "cpu", N_PLACEHOLDER).modules, notes


def build_refine(cfg) -> tuple[dict[str, nn.Module | None], list[str]]:
    from nsplat.data.views import PosedViews
    from nsplat.tasks import refine

    count = cfg.data.room.frames if cfg.data.source == "room" else max(1, cfg.data.nerf.limit)
    C = cfg.scene.channels
    frames = PosedViews(images=torch.zeros(count, 1, 1, C), viewmats=torch.eye(4).expand(count, 4, 4).clone(),
                        Ks=torch.eye(3).expand(count, 3, 3).clone(), names=[str(i) for i in range(count)],
                        masks=torch.ones(count, 1, 1, dtype=torch.bool))
    modules = refine.build(cfg, _placeholder_scene(cfg.scene), frames).modules
    modules["model"].frames = None  # data, not model state
    notes = [f"cameras: {count} frames (source {cfg.data.source}); shading: {cfg.shading.model}"]
    return modules, notes


def build_neural(cfg) -> tuple[dict[str, nn.Module | None], list[str]]:
    from nsplat import fitting
    from nsplat.tasks import neural

    stage1 = fitting.build(_placeholder_scene(neural.geometry_scene_config(cfg)), cfg.geometry.optim).modules
    stage2 = neural.build(cfg, _placeholder_scene(neural.neural_scene_config(cfg))).modules
    disc = stage2.get("disc")
    notes = [f"stage 1 (geometry): RGB surfels; stage 2: {cfg.neural.features} learned features per point, "
             f"U-Net shader, PatchGAN {'on' if disc is not None else 'off (not built)'}",
             f"N = visual-hull points (at most geometry.max_points = {cfg.geometry.max_points})"]
    return {"stage1_scene": stage1["scene"], "stage2": stage2["model"], "discriminator": disc}, notes


BUILDERS: dict[str, Callable[[Any], tuple[dict[str, nn.Module | None], list[str]]]] = {
    "demo": build_demo, "reconstruct": build_reconstruct, "refine": build_refine, "neural": build_neural,
}


def build_config(path: Path, overrides: list[str] | None = None) -> tuple[str, Any, dict[str, nn.Module | None],
                                                                          list[str]]:
    """``(task, cfg, models, notes)`` of config file ``path`` with dotted ``key=value`` overrides."""
    raw = read_yaml(path)
    task = get_task(raw["task"])
    cfg = load_config(task.Config, raw, overrides)
    if raw["task"] not in BUILDERS:
        raise KeyError(f"{path.name}: no allocation builder for task {raw['task']!r} (add one to BUILDERS)")
    models, notes = BUILDERS[raw["task"]](cfg)
    return raw["task"], cfg, models, notes


def _summary(entries: list[Entry]) -> dict[str, Any]:
    learned_pp = sum(e.floats() for e in entries if e.per_point and e.learned)
    fixed_pp = sum(e.floats() for e in entries if e.per_point and not e.learned)
    learned_global = sum(e.floats() for e in entries if not e.per_point and e.learned)
    fixed_global = sum(e.floats() for e in entries if not e.per_point and not e.learned)
    return dict(learned_pp=learned_pp, fixed_pp=fixed_pp, learned_global=learned_global, fixed_global=fixed_global)


def _group(entries: list[Entry]) -> list[tuple[str, int, int, bool]]:
    """Network-sized modules collapsed: (module, tensors, floats, learned) for non-per-point entries."""
    groups: dict[str, list[Entry]] = {}
    for e in entries:
        top = ".".join(e.module.split(".")[:2])
        groups.setdefault(top, []).append(e)
    out = []
    for top, es in groups.items():
        out.append((top, len(es), sum(x.floats() for x in es), any(x.learned for x in es)))
    return out


def render_markdown(rows: list[tuple[str, str, list[Entry], list[str]]]) -> str:
    lines = [
        "# What each shipped config allocates and learns",
        "",
        "Generated by `python benchmarks/allocation_table.py` (do not edit by hand). Each config's model is",
        "built as its task builds it, without data or training; `N` is the number of points. A tensor is",
        "*learned* when it is an `nn.Parameter` with `requires_grad`; other tensors are buffers (frozen, saved",
        "in checkpoints unless marked non-persistent). Attributes a config makes constant (e.g. `scene.opacity:",
        "1.0`, `scene.scale: 0.01`) and features a task does not use (neural features, SH lighting, pose or",
        "focal corrections, a discriminator) are not allocated at all; `tests/test_allocation.py` checks this.",
        "",
        "## Summary",
        "",
        "Per model (a task's stages are separate models: the neural task's stage-1 geometry scene is",
        "replaced by the stage-2 model).",
        "",
        "| config | task | model | learned floats / point | frozen floats / point | learned global floats "
        "| frozen global floats |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for name, task, entries, _ in rows:
        labels = list(dict.fromkeys(e.module.split(".")[0] for e in entries)) or ["(none)"]
        for label in labels:
            s = _summary([e for e in entries if e.module.split(".")[0] == label])
            lines.append(f"| `{name}` | {task} | {label} | {s['learned_pp']} | {s['fixed_pp']} | "
                         f"{s['learned_global']:,} | {s['fixed_global']:,} |")
    for name, task, entries, notes in rows:
        lines += ["", f"## `{name}` (task `{task}`)", ""]
        lines += [f"- {n}" for n in notes]
        if not entries:
            lines += ["", "Nothing allocated (no parameters, no buffers)."]
            continue
        lines += ["", "| tensor | shape | learned | floats |", "|---|---|:---:|---:|"]
        for e in entries:
            if not _is_network(e):
                per = f"{e.floats()} / point" if e.per_point else f"{e.floats():,}"
                flag = "yes" if e.learned else ("no" if e.persistent else "no (not saved)")
                lines.append(f"| `{e.module}.{e.name}` | {e.shape_text()} | {flag} | {per} |")
        nets = [g for g in _group([e for e in entries if _is_network(e)])]
        for top, count, floats, learned in nets:
            lines.append(f"| `{top}.*` ({count} tensors) | network | {'yes' if learned else 'no'} | {floats:,} |")
    return "\n".join(lines) + "\n"


def _is_network(e: Entry) -> bool:
    """Tensors of networks (U-Net, PatchGAN) are summarised per network instead of listed one by one."""
    parts = e.module.split(".")
    return (len(parts) >= 2 and parts[1] == "unet") or parts[0] == "discriminator"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--configs", type=Path, default=ROOT / "configs")
    p.add_argument("--out", type=Path, default=DOC)
    p.add_argument("--check", action="store_true", help="compare with the existing doc instead of writing it")
    args = p.parse_args(argv)
    rows = []
    for path in sorted(args.configs.glob("*.yaml")):
        task, _cfg, models, notes = build_config(path)
        rows.append((path.name, task, inventory(models), notes))
    text = render_markdown(rows)
    if args.check:
        same = args.out.is_file() and args.out.read_text() == text
        print("up to date" if same else f"{args.out} is out of date; run benchmarks/allocation_table.py")
        return 0 if same else 1
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)
    print(f"wrote {args.out} ({len(rows)} configs; tasks registered: {sorted(TASKS)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

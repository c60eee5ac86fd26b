"""Across scenes: the point-only and the neural recipe on every scene the data root holds (issue 70).

For each scene, two runs of ``train.py`` with the settings a user would take for it, and nothing tuned on it:

* **NeRF-synthetic** scenes found as ``$NSPLAT_DATA/nerf_synthetic/<scene>_400`` (``nsplat data fetch
  nerf_synthetic --resolution 400``): ``configs/nerf_synthetic.yaml data.scene=<scene>`` (neural) and the same
  with ``neural.steps=0`` on lego_splat_only's 72-epoch schedule (point-only); lego's own box is not used, the
  scene's box comes from its silhouettes.
* **Procedural** scenes (always there, generated on first use): the main job's (``configs/default.yaml``, point-only
  ``configs/splat_only.yaml``), the same scene moved by a rigid transform of its cameras far outside the cube the
  recipe once carved in (``moved``: the images are the same bits, only the world frame changes), and another
  seed (``seed7``).

Per run: held-out test PSNR / SSIM / LPIPS (the standard protocol), the final validation PSNR, the point count,
wall and CPU time. ``benchmarks/results/scenes.json`` keeps every row (runs of other scenes are merged into it);
the table goes to docs/results.md ("Across scenes").

    python -m benchmarks.scenes                          # the procedural scenes, and NeRF-synthetic ones found
    python -m benchmarks.scenes --scenes main moved      # some of them
    python -m benchmarks.scenes --smoke                  # CI: the main scene, a few steps
"""
from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from plyfile import PlyData

from benchmarks.common import REPO, markdown, read_result, run_config, write_result
from nsplat.data.nerf_scenes import NERF_SCENES
from nsplat.data.paths import data_root
from nsplat.data.procedural import ProceduralSpec, ensure_scene

#: The rigid transform of the ``moved`` scene: 40° about (1, 2, 2)/3, then a shift that puts the objects about
#: 3.2 units from the origin (outside the former fixed box [-1.5, 1.5]³).
MOVE_AXIS, MOVE_DEGREES, MOVE_SHIFT = (1.0, 2.0, 2.0), 40.0, (2.5, -1.5, 1.2)
#: Point-only overrides of a NeRF-synthetic scene (lego_splat_only's schedule).
NERF_POINT_ONLY = ["neural.steps=0", "geometry.optim.epochs=72", "geometry.optim.anneal_epochs=12"]


def _rotation(axis: tuple[float, float, float], degrees: float) -> np.ndarray:
    """``[3,3]`` rotation by ``degrees`` about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(degrees)
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K


def moved_copy(src: Path, dst: Path) -> Path:
    """``dst``: the NeRF-synthetic-layout scene ``src`` with every camera moved by :data:`MOVE_AXIS` …: the
    ``transform_matrix`` (camera to world) left-multiplied by the rigid transform; the images are links."""
    R, shift = _rotation(MOVE_AXIS, MOVE_DEGREES), np.asarray(MOVE_SHIFT)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, shift
    dst.mkdir(parents=True, exist_ok=True)
    for entry in src.iterdir():
        target = dst / entry.name
        if entry.name.startswith("transforms_") and entry.suffix == ".json":
            meta = json.loads(entry.read_text())
            for frame in meta["frames"]:
                frame["transform_matrix"] = (T @ np.asarray(frame["transform_matrix"])).tolist()
            target.write_text(json.dumps(meta, indent=1))
        elif not target.exists():
            target.symlink_to(entry.resolve())
    return dst


def procedural_folder(seed: int, cache: Path) -> Path:
    """The main job's procedural scene (64², 40/8/8 views, 4 objects) of ``seed``, generated on first use."""
    return ensure_scene(ProceduralSpec(seed=seed, resolution=64, views=(40, 8, 8), objects=4), cache)


def _procedural_source(root: Path) -> list[str]:
    return ["data.source=nerf_synthetic", f"data.root={root}", "data.resolution=null"]


def scene_runs(names: list[str] | None, cache: Path) -> dict[str, dict[str, tuple[str, list[str]]]]:
    """Scene → ``{kind: (config, overrides)}`` for the scenes asked for (``None``: the procedural ones and every
    NeRF-synthetic scene on disk)."""
    out: dict[str, dict[str, tuple[str, list[str]]]] = {}
    wanted = set(names) if names else None
    for name in ("main", "moved", "seed7"):
        if wanted is not None and name not in wanted:
            continue
        source = {"main": [], "seed7": ["data.procedural.seed=7"]}.get(name)
        if source is None:
            source = _procedural_source(moved_copy(procedural_folder(0, cache), cache / "moved"))
        out[name] = {"point-only": ("splat_only", source), "neural": ("default", source)}
    for name in NERF_SCENES:
        if (wanted is None and (data_root() / "nerf_synthetic" / f"{name}_400").is_dir()) or \
                (wanted is not None and name in wanted):
            scene = [f"data.scene={name}"]
            out[name] = {"point-only": ("nerf_synthetic", scene + NERF_POINT_ONLY),
                         "neural": ("nerf_synthetic", scene)}
    if wanted is not None and (missing := wanted - set(out)):
        raise SystemExit(f"--scenes: unknown {sorted(missing)}; expected main, moved, seed7 or one of "
                         f"{list(NERF_SCENES)}")
    return out


def _json(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text()) if path.is_file() else {}


def summarise(run: Path, kind: str) -> dict[str, Any]:
    """Held-out test metrics, final val PSNR and point count of a finished run folder."""
    if kind == "point-only":
        test = _json(run / "eval_geometry.json").get("test", {})
        curve = _json(run / "geometry_history.json").get("history", [])
    else:
        test = _json(run / "eval_test" / "metrics.json")
        curve = _json(run / "history.json").get("history", [])
    lpips = test.get("lpips", {}).get("vgg")
    return {"test_psnr": test["psnr"]["mean"], "test_psnr_std": test["psnr"]["std"], "test_ssim": test["ssim"]["mean"],
            "test_lpips_vgg": lpips.get("mean") if isinstance(lpips, dict) else None,
            "lpips_note": None if isinstance(lpips, dict) else lpips,
            "val_psnr": curve[-1]["val_psnr"] if curve else None,
            "points": PlyData.read(str(run / "geometry.ply"))["vertex"].count}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="*", help="scene names (default: the procedural ones and the NeRF-synthetic "
                                                "scenes under the data root)")
    ap.add_argument("--runs", type=Path, default=Path("runs/bench-scenes"), help="where the run folders go")
    ap.add_argument("--smoke", action="store_true",
                    help="the main scene's two recipes, one epoch, runs in a temporary folder (CI)")
    args = ap.parse_args(argv)
    cache = Path(tempfile.gettempdir()) / "nsplat-bench-scenes"
    runs = scene_runs(["main"] if args.smoke else args.scenes, cache)
    runs_dir = Path(tempfile.mkdtemp(prefix="nsplat-scenes-")) if args.smoke else args.runs
    short = {"point-only": ["geometry.optim.epochs=1", "geometry.optim.anneal_epochs=0"],
             "neural": ["geometry.optim.epochs=1", "neural.steps=2", "log.validate=2"]} if args.smoke else {}
    record = (read_result("scenes") or {}) if not args.smoke else {}
    rows = {**record.get("rows", {})}
    for scene, kinds in runs.items():
        for kind, (config, overrides) in kinds.items():
            run = runs_dir / f"{scene}-{kind}"
            cost = run_config(REPO / "configs" / f"{config}.yaml", run, overrides + short.get(kind, []))
            rows[f"{scene}/{kind}"] = {"scene": scene, "kind": kind, "config": f"configs/{config}.yaml",
                                       "overrides": overrides, **summarise(run, kind),
                                       "wall_s": cost["wall_s"], "cpu_s": cost["cpu_s"],
                                       "load_avg": [cost["load_before"][0], cost["load_after"][0]]}
            print(f"{scene} {kind}: {rows[f'{scene}/{kind}']['test_psnr']:.2f} dB", flush=True)
    ordered = sorted(rows.values(), key=lambda r: (r["scene"], r["kind"]))
    table = markdown(
        ["scene", "model", "test PSNR (dB)", "SSIM", "LPIPS (VGG)", "final val PSNR", "points", "wall / CPU (s)"],
        [[r["scene"], r["kind"], f"{r['test_psnr']:.2f} ± {r['test_psnr_std']:.2f}", f"{r['test_ssim']:.4f}",
          "—" if r["test_lpips_vgg"] is None else f"{r['test_lpips_vgg']:.3f}",
          "—" if r["val_psnr"] is None else f"{r['val_psnr']:.2f}", r["points"],
          f"{r['wall_s']:.0f} / {r['cpu_s']:.0f}"] for r in ordered])
    write_result("scenes" if not args.smoke else "scenes-smoke",
                 {"rows": rows, "move": {"axis": MOVE_AXIS, "degrees": MOVE_DEGREES, "shift": MOVE_SHIFT}}, table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

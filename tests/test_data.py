"""Data: NeRF-synthetic loader conventions, the procedural scene generator and its ray tracer."""
from __future__ import annotations

import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from nsplat.cameras import intrinsics_from_fov, look_at, opengl_c2w_to_viewmat
from nsplat.data import ProceduralSpec, ensure_scene, generate, load_split
from nsplat.data.procedural import viewmat_to_opengl_c2w
from nsplat.data.raytrace import Box, Light, Material, Plane, Sphere, intersect, render
from nsplat.data.visual_hull import carve


def _project(viewmat: torch.Tensor, K: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    q = viewmat[:3, :3].double() @ X.double() + viewmat[:3, 3].double()
    return (K.double() @ (q / q[2]))[:2]


def _hand_made_scene(root: Path) -> None:
    """One 20×10 RGBA frame; camera at (0, 0, 4) looking down world -z (OpenGL c2w = translation),
    ``f = 20 px``; an opaque red pixel where world (0.5, 0.25, 0) lands, a half-transparent blue one,
    the rest transparent."""
    (root / "train").mkdir(parents=True)
    fov = 2.0 * math.atan(0.5 * 20 / 20.0)  # f = W / 2 / tan(fov / 2) = 20 px
    c2w = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0], [0.0, 0.0, 0.0, 1.0]]
    (root / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": fov, "frames": [{"file_path": "./train/r_0", "transform_matrix": c2w}]}))
    img = np.zeros((10, 20, 4), np.uint8)
    img[3, 12] = (255, 0, 0, 255)   # u = 10 + 20·0.5/4 = 12.5, v = 5 - 20·0.25/4 = 3.75
    img[8, 2] = (0, 0, 255, 128)
    iio.imwrite(root / "train" / "r_0.png", img)


def test_loader_known_point_projects_to_known_pixel(tmp_path):
    _hand_made_scene(tmp_path)
    v = load_split(tmp_path, "train")
    assert v.images.shape == (1, 10, 20, 3) and v.masks.shape == (1, 10, 20)
    X = torch.tensor([0.5, 0.25, 0.0])  # right of and above the optical axis (world y is up)
    uv = _project(v.viewmats[0], v.Ks[0], X)
    assert torch.allclose(uv, torch.tensor([12.5, 3.75], dtype=torch.float64), atol=1e-5)
    col, row = int(uv[0]), int(uv[1])
    assert torch.allclose(v.images[0, row, col], torch.tensor([1.0, 0.0, 0.0]))
    # White background under transparent pixels, alpha compositing of the half-transparent one.
    assert torch.allclose(v.images[0, 0, 0], torch.ones(3))
    a = 128 / 255
    assert torch.allclose(v.images[0, 8, 2], torch.tensor([1 - a, 1 - a, 1.0]), atol=1e-6)
    assert v.masks[0, 8, 2].item() == pytest.approx(a)
    # Viewmats are exact world→camera matrices (last row exact, as the op checks).
    assert torch.equal(v.viewmats[0, 3], torch.tensor([0.0, 0.0, 0.0, 1.0]))


def test_loader_resize_scales_intrinsics_and_background(tmp_path):
    _hand_made_scene(tmp_path)
    v = load_split(tmp_path, "train", resolution=(10, 5), background=(0.0, 0.0, 0.0))
    assert v.images.shape == (1, 5, 10, 3)
    uv = _project(v.viewmats[0], v.Ks[0], torch.tensor([0.5, 0.25, 0.0]))
    assert torch.allclose(uv, torch.tensor([6.25, 1.875], dtype=torch.float64), atol=1e-5)
    # 2×2 area averaging of the red pixel (rows 2-3, cols 12-13) on black.
    assert torch.allclose(v.images[0, 1, 6], torch.tensor([0.25, 0.0, 0.0]), atol=1e-6)


def test_loader_errors_name_the_argument(tmp_path):
    _hand_made_scene(tmp_path)
    with pytest.raises(ValueError, match="split"):
        load_split(tmp_path, "training")
    with pytest.raises(FileNotFoundError, match="transforms_test.json"):
        load_split(tmp_path, "test")
    with pytest.raises(ValueError, match="background"):
        load_split(tmp_path, "train", background=(2.0, 0.0, 0.0))


def test_opengl_roundtrip():
    V = look_at(torch.tensor([[1.0, -2.0, 3.0]], dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64),
                torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    assert torch.allclose(opengl_c2w_to_viewmat(viewmat_to_opengl_c2w(V)), V, atol=1e-12)


def test_raytracer_sphere_lands_where_the_camera_model_says():
    """The ray tracer and the library's camera model agree: a small sphere's coverage centroid is
    the projection of its centre, and its radius matches the pinhole prediction."""
    W, H = 48, 40
    K = torch.tensor([[60.0, 0.0, 20.0], [0.0, 60.0, 22.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    V = look_at(torch.tensor([[0.3, -4.0, 1.0]], dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64),
                torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))[0]
    c = torch.tensor([0.4, 0.2, 0.3], dtype=torch.float64)
    s = Sphere(centre=tuple(c.tolist()), radius=0.15, material=Material("solid", (1.0, 1.0, 1.0)))
    rgba = render([s], Light(ambient=1.0, intensity=0.0), V, K, W, H, supersample=4)
    a = rgba[..., 3]
    rows, cols = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                                indexing="ij")
    centroid = torch.stack([(a * cols).sum(), (a * rows).sum()]) / a.sum()
    assert torch.allclose(centroid, _project(V, K, c), atol=0.1)
    depth = (V[:3, :3] @ c + V[:3, 3])[2]
    assert math.sqrt(float(a.sum()) / math.pi) == pytest.approx(60.0 * 0.15 / float(depth), rel=0.03)
    assert torch.allclose(rgba[a == 1][:, :3], torch.ones(3, dtype=torch.float64))  # ambient-only white


def test_raytracer_primitives_hit_distances():
    o = torch.tensor([[0.0, 0.0, 5.0], [0.0, 0.0, 5.0], [3.0, 0.0, 0.5]], dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]], dtype=torch.float64)
    box = Box(centre=(0.0, 0.0, 0.5), half=(0.5, 0.5, 0.5), yaw=math.pi / 4, material=Material())
    hit = intersect(o, d, [box])
    assert hit.t[0].item() == pytest.approx(4.0)                      # top face at z = 1
    assert torch.allclose(hit.normal[0], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    assert hit.t[2].item() == pytest.approx(3.0 - 0.5 * math.sqrt(2))  # rotated corner on the x axis
    plane = Plane(centre=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0), half=(1.0, 1.0), material=Material())
    miss = intersect(torch.tensor([[2.0, 0.0, 5.0]], dtype=torch.float64), d[:1], [plane])
    assert miss.prim.item() == -1 and math.isinf(miss.t.item())


def test_procedural_generator_is_deterministic(tmp_path):
    spec = ProceduralSpec(seed=3, resolution=16, views=(3, 1, 2), supersample=1)
    a, b = generate(spec, tmp_path / "a"), generate(spec, tmp_path / "b")
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(files) == 3 + 1 + 2 + 3 + 1  # PNGs, three transforms files, scene.json
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    other = generate(ProceduralSpec(seed=4, resolution=16, views=(3, 1, 2), supersample=1), tmp_path / "c")
    assert (other / "train" / "r_0.png").read_bytes() != (a / "train" / "r_0.png").read_bytes()


def test_procedural_scene_loads_and_is_cached(tmp_path):
    spec = ProceduralSpec(seed=1, resolution=24, views=(6, 2, 2))
    root = ensure_scene(spec, tmp_path)
    mtime = (root / "train" / "r_0.png").stat().st_mtime_ns
    assert ensure_scene(spec, tmp_path) == root
    assert (root / "train" / "r_0.png").stat().st_mtime_ns == mtime  # not regenerated
    assert [p.name for p in tmp_path.iterdir()] == [root.name]       # no temporaries left
    v = load_split(root, "train")
    assert v.images.shape == (6, 24, 24, 3)
    assert torch.allclose(v.Ks[0], intrinsics_from_fov(spec.camera_angle_x, 24, 24)[0])
    covered = v.masks.mean().item()
    assert 0.03 < covered < 0.8  # objects fill part of the frame, background is transparent
    # Every object is seen: the silhouettes' visual hull is not empty and lies within the scene box.
    occ = carve(v, (-1.5, -1.5, -0.2, 1.5, 1.5, 1.6), 24)
    assert 0 < occ.sum() < occ.size // 4


def test_procedural_spec_validation():
    with pytest.raises(ValueError, match="views"):
        ProceduralSpec(views=(2, 0, 1))
    with pytest.raises(ValueError, match="resolution"):
        ProceduralSpec(resolution=4)

"""The training frame of a capture (nsplat/tasks/neural/frame.py) on synthetic rigs: it sits on the object the
views see whatever the cameras aim at, and it is the same whatever similarity the SfM world is off by."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from nsplat.cameras import camera_centres, look_at, look_at_point
from nsplat.data.capture import SfmPoints
from nsplat.data.views import PosedViews
from nsplat.tasks.neural.frame import MIN_SPREAD, capture_frame, geometric_median

SIZE, FOCAL = 64, 50.0  # 65° field of view
UP = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def _rig(kind: str, aim: tuple[float, float, float] = (0.0, 0.0, 0.0), count: int = 30) -> torch.Tensor:
    """``[count,4,4]`` cameras about an object at the origin (z up): ``hemisphere`` (elevation 10-70°), ``orbit``
    (-30-30°), both 4 units from ``aim`` and looking at it, or ``forward`` (a 6×5 grid in the plane y = -4, all
    looking along +y)."""
    rng = np.random.default_rng(1)
    if kind == "forward":
        x, z = np.meshgrid(np.linspace(-1.0, 1.0, 6), np.linspace(-0.6, 0.6, 5))
        eye = torch.tensor(np.stack([x.ravel(), np.full(x.size, -4.0), z.ravel()], 1))
        target = eye + torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
        return look_at(eye, target, UP)
    lo, hi = (10.0, 70.0) if kind == "hemisphere" else (-30.0, 30.0)
    az = (np.arange(count) + rng.uniform(0, 1, count)) / count * 2 * math.pi
    el = np.radians(rng.uniform(lo, hi, count))
    target = torch.tensor(aim, dtype=torch.float64)
    eye = 4.0 * torch.tensor(np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)) + target
    return look_at(eye, target.expand(count, 3), UP)


def _points(object_points: int = 1500, backdrop: int = 1500) -> torch.Tensor:
    """``[P,3]`` float64: a textured object (a ball of radius 0.7 at the origin) and a far backdrop (a sphere of
    radius 12 about it)."""
    g = torch.Generator().manual_seed(0)
    ball = torch.nn.functional.normalize(torch.randn(object_points, 3, generator=g, dtype=torch.float64), dim=1)
    ball = ball * 0.7 * torch.rand(object_points, 1, generator=g, dtype=torch.float64) ** (1 / 3)
    far = 12.0 * torch.nn.functional.normalize(torch.randn(backdrop, 3, generator=g, dtype=torch.float64), dim=1)
    return torch.cat([ball, far])


def _views(viewmats: torch.Tensor) -> PosedViews:
    K = torch.tensor([[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1]]).expand(len(viewmats), 3, 3)
    return PosedViews(images=torch.empty(len(viewmats), SIZE, SIZE, 0), viewmats=viewmats.float(), Ks=K.clone(),
                      names=[f"im_{i:03d}.png" for i in range(len(viewmats))])


def _sfm(xyz: torch.Tensor) -> SfmPoints:
    n = len(xyz)
    return SfmPoints(xyz=xyz.float(), rgb=torch.full((n, 3), 0.5), track_length=torch.full((n,), 5),
                     error=torch.full((n,), 0.5))


def _similar(viewmats: torch.Tensor, xyz: torch.Tensor, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The rig and points in a world moved by a random similarity ``x → s R x + t`` (``s`` in [0.05, 20], ``t``
    up to 50 units): what another SfM run may pick."""
    rng = np.random.default_rng(seed)
    s = float(np.exp(rng.uniform(math.log(0.05), math.log(20.0))))
    R = torch.tensor(Rotation.random(random_state=rng).as_matrix())
    t = torch.tensor(rng.uniform(-50.0, 50.0, 3))
    V = viewmats.double().clone()
    V[:, :3, :3] = viewmats[:, :3, :3].double() @ R.T     # x_cam = Rc x + tc = Rc Rᵀ (x' − t)/s + tc
    V[:, :3, 3] = s * viewmats[:, :3, 3].double() - V[:, :3, :3] @ t
    return V, s * xyz.double() @ R.T + t


@pytest.mark.parametrize("kind", ["hemisphere", "orbit", "forward"])
def test_frame_is_the_same_whatever_similarity_the_sfm_world_is_off_by(kind):
    V, xyz = _rig(kind), _points()
    ref = capture_frame(_views(V), _sfm(xyz), radius=3.2)
    assert ref.source == "points" and ref.core > 1000
    for seed in range(3):
        V2, xyz2 = _similar(V, xyz, seed)
        f = capture_frame(_views(V2), _sfm(xyz2), radius=3.2)
        assert f.source == ref.source and f.core == ref.core
        # the same training frame: points and cameras land on the same coordinates (float32 in the SfM world)
        assert (f.points(xyz2) - ref.points(xyz)).abs().max().item() < 2e-4 * 12 * 3.2 / ref.radius
        assert (f.viewmats(V2) - ref.viewmats(V)).abs().max().item() < 1e-4
    # z is the cameras' up, the median camera 3.2 from the centre: on the object, or for the forward-facing rig
    # between the object and the backdrop behind it, which the views also see in their middle
    assert torch.allclose(ref.rotation[2], UP, atol=0.02)      # the mean up of cameras aimed at the object
    if kind == "forward":
        assert 0.0 < ref.centre[1].item() < 12.0 and ref.centre[[0, 2]].norm().item() < 0.1
    else:
        assert ref.points(torch.zeros(1, 3)).norm().item() < 0.05
    assert camera_centres(ref.viewmats(V).double()).norm(dim=1).median().item() == pytest.approx(3.2, rel=1e-5)


def test_frame_sits_on_the_object_when_the_cameras_aim_above_it():
    """A table capture framed high: every camera aims 1.2 units above the object (0.3 camera distances), which
    still shows in every photo; the look-at point is the aim, the frame's centre the object."""
    V, xyz = _rig("hemisphere", aim=(0.0, 0.0, 1.2)), _points()
    f = capture_frame(_views(V), _sfm(xyz), radius=3.2)
    assert torch.allclose(f.look_at, torch.tensor([0.0, 0.0, 1.2], dtype=torch.float64), atol=1e-6)
    assert f.source == "points" and f.centre.norm().item() < 0.05
    assert f.diagnosis()["look_at_offset_radii"] == pytest.approx(1.2 / f.radius, rel=0.05)


def test_without_object_points_the_look_at_point_places_the_centre():
    """An untextured object before a textured backdrop (the procedural capture): no point is seen near the middle
    of most views, so the cameras' aim decides; for parallel axes (forward-facing), which do not meet, the points'
    geometric median does."""
    V, xyz = _rig("hemisphere", aim=(0.0, 0.0, 0.3)), _points(object_points=0)
    f = capture_frame(_views(V), _sfm(xyz), radius=3.2)
    assert f.source == "look-at" and f.core == 0
    assert torch.allclose(f.centre, torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64), atol=1e-6)
    F = _rig("forward")
    assert look_at_point(F)[1] < MIN_SPREAD
    g = torch.Generator().manual_seed(0)
    y = 6.0 + 24.0 * torch.rand(400, generator=g, dtype=torch.float64)     # a cone about the view direction,
    a = 2 * math.pi * torch.rand(400, generator=g, dtype=torch.float64)    # seen at the images' edges only
    cone = torch.stack([0.7 * (y + 4) * torch.cos(a), y, 0.7 * (y + 4) * torch.sin(a)], 1)
    f = capture_frame(_views(F), _sfm(cone), radius=3.2)
    assert f.source == "all points"
    assert torch.allclose(f.centre, geometric_median(cone, torch.ones(400, dtype=torch.float64)), atol=1e-9)
    assert capture_frame(_views(V), None, radius=3.2).source == "look-at"


def test_geometric_median_ignores_outliers_and_moves_with_the_points():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(300, 3, generator=g, dtype=torch.float64) * 0.1
    x[:40] += 100.0                                          # 13 % far outliers
    m = geometric_median(x, torch.ones(300, dtype=torch.float64))
    assert m.norm().item() < 0.05
    R = torch.tensor(Rotation.random(random_state=3).as_matrix())
    m2 = geometric_median(2.5 * x @ R.T + 7.0, torch.ones(300, dtype=torch.float64))
    assert torch.allclose(m2, 2.5 * R @ m + 7.0, atol=1e-6)

"""Initialisation of a capture without masks: surfels from SfM points (:mod:`nsplat.tasks.neural.sfm_init`: outlier
filters, plane-fit normals, neighbour-spacing scales) on known synthetic clouds, and the background
sphere (:mod:`nsplat.tasks.neural.background`: frame, lattice, colours from the photos, near/far)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nsplat.cameras import camera_centres, look_at, look_at_point
from nsplat.data.capture import SfmPoints
from nsplat.data.views import PosedViews
from nsplat.tasks.neural.background import depth_range, fibonacci_sphere, fit_sphere, project, sphere_background
from nsplat.tasks.neural.sfm_init import fill_box, fill_points, isolated, plane_normals, reliable, sfm_surfels


def _points(xyz: np.ndarray, track: np.ndarray | None = None, error: np.ndarray | None = None) -> SfmPoints:
    n = len(xyz)
    return SfmPoints(xyz=torch.from_numpy(xyz).float(), rgb=torch.linspace(0, 1, n)[:, None].expand(n, 3).clone(),
                     track_length=torch.as_tensor(np.full(n, 5) if track is None else track, dtype=torch.int64),
                     error=torch.as_tensor(np.full(n, 0.5) if error is None else error, dtype=torch.float32))


def _grid(spacing: float, side: int = 20) -> np.ndarray:
    """A square grid of ``side²`` points with ``spacing`` in the plane z = 0."""
    u = (np.arange(side) - (side - 1) / 2) * spacing
    x, y = np.meshgrid(u, u)
    return np.stack([x.ravel(), y.ravel(), np.zeros(side * side)], 1)


def _cameras(count: int = 12, radius: float = 4.0, height: float = 2.0) -> torch.Tensor:
    """``[count,4,4]`` cameras on a circle above the origin, all looking at it."""
    a = torch.arange(count, dtype=torch.float64) * 2 * math.pi / count
    eye = torch.stack([radius * torch.cos(a), radius * torch.sin(a), torch.full_like(a, height)], 1)
    return look_at(eye, torch.zeros(count, 3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def test_plane_fit_normals_of_a_tilted_noisy_plane():
    g = np.random.default_rng(0)
    pts = _grid(0.05) + g.normal(0, 0.002, (400, 3))
    n_true = np.array([0.3, -0.2, 0.93])
    n_true /= np.linalg.norm(n_true)
    # rotate z onto n_true (Rodrigues), so the plane's normal is n_true
    v, c = np.cross([0, 0, 1.0], n_true), n_true[2]
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    R = np.eye(3) + vx + vx @ vx / (1 + c)
    normals = plane_normals(pts @ R.T, k=8)
    cos = np.abs(normals @ n_true)
    assert np.median(cos) > 0.995 and cos.min() > 0.95
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)


def test_scales_follow_the_neighbour_spacing_and_normals_face_the_cameras():
    fine, coarse = _grid(0.02, 10), _grid(0.1, 10) + [3.0, 0.0, 0.0]
    pts = _points(np.concatenate([fine, coarse]))
    centres = torch.tensor([[0.0, 0.0, 5.0], [1.0, 0.0, 4.0]])
    sf = sfm_surfels(pts, centres, std_ratio=10.0, max_spacing_quantile=1.0)
    assert len(sf.index) == 200
    # 3-NN mean spacing on a square grid: interior points (1, 1, 1) × spacing, edges more
    assert torch.median(sf.spacing[:100]).item() == pytest.approx(0.02, rel=0.01)
    assert torch.median(sf.spacing[100:]).item() == pytest.approx(0.1, rel=0.01)
    assert bool((sf.normals[:, 2] > 0.99).all())          # the cameras are above the plane
    assert torch.equal(sf.colours, pts.rgb[sf.index])


def test_spacing_is_capped_at_its_quantile():
    pts = _points(np.concatenate([_grid(0.02, 10), [[0.5, 0.5, 0.0], [0.9, -0.9, 0.0]]]))
    sf = sfm_surfels(pts, torch.tensor([[0.0, 0.0, 5.0]]), std_ratio=100.0, max_spacing_quantile=0.9)
    assert len(sf.index) == 102
    assert sf.spacing.max().item() == pytest.approx(float(np.quantile(sf.spacing.numpy(), 0.9)), rel=1e-5)
    assert sf.spacing.max().item() < 0.1                   # the two far points would be ~0.5 otherwise


def test_outliers_by_track_length_error_and_isolation_are_removed():
    g = np.random.default_rng(1)
    cloud = _grid(0.05)                                    # 400 good points
    far = g.uniform(-1, 1, (6, 3)) * 3 + [0, 0, 5.0]       # isolated points floating above
    xyz = np.concatenate([cloud, far])
    track = np.full(len(xyz), 4)
    error = np.full(len(xyz), 0.7)
    track[:10] = 2                                         # two-view points
    error[10:20] = 3.5                                     # poorly reprojected
    error[20:25] = -1.0                                    # unknown error: kept
    pts = _points(xyz, track, error)
    ok = reliable(pts, min_track=3, max_error=2.0)
    assert ok.sum().item() == len(xyz) - 20 and not bool(ok[:20].any()) and bool(ok[20:25].all())
    sf = sfm_surfels(pts, torch.tensor([[0.0, 0.0, 10.0]]), min_track=3, max_error=2.0)
    kept = set(sf.index.tolist())
    assert kept.isdisjoint(range(20))
    assert kept.isdisjoint(range(400, 406))                # every isolated point is gone
    assert len(kept) >= 380 - 10                           # and (almost) no good one
    lonely = isolated(xyz[20:], k=8, std_ratio=2.0)
    assert lonely[-6:].all() and lonely[:-6].mean() < 0.03


def test_too_few_reliable_points_is_a_clear_error():
    pts = _points(_grid(0.05, 4), track=np.full(16, 2))
    with pytest.raises(ValueError, match="track length >= 3"):
        sfm_surfels(pts, torch.zeros(1, 3))


def test_look_at_point_is_where_the_optical_axes_meet():
    V = _cameras(radius=4.0, height=3.0)
    shift = torch.tensor([0.5, -0.2, 0.3], dtype=torch.float64)
    V2 = V.clone()
    V2[:, :3, 3] = V[:, :3, 3] - (V[:, :3, :3] @ shift)  # the same rig moved by +shift
    centre, spread = look_at_point(V2)
    assert torch.allclose(centre, shift, atol=1e-9)
    assert (camera_centres(V2.double()) - centre).norm(dim=1).median().item() == pytest.approx(5.0, rel=1e-9)
    assert 0.1 < spread <= 2 / 3
    assert torch.allclose(camera_centres(V2.double()).mean(0)[:2], shift[:2], atol=1e-9)


def test_fibonacci_sphere_is_even():
    d = fibonacci_sphere(2000)
    assert torch.allclose(d.norm(dim=1), torch.ones(2000, dtype=torch.float64))
    assert d.mean(0).norm().item() < 1e-3                  # balanced
    nn = torch.cdist(d, d).fill_diagonal_(9).min(1).values
    assert nn.max() / nn.min() < 1.6                       # no clumps, no holes


def _sky_views(size: int = 24) -> PosedViews:
    """Views of a world whose colour depends only on the direction: red above the horizon, blue below."""
    V = _cameras(radius=3.0, height=0.0).float()
    f = size / 2 / math.tan(math.radians(30))
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]]).expand(len(V), 3, 3).clone()
    img = torch.zeros(len(V), size, size, 3)
    img[:, : size // 2, :, 0] = 1.0                        # top half (above the horizon): red
    img[:, size // 2:, :, 2] = 1.0                         # bottom half: blue
    return PosedViews(images=img, viewmats=V, Ks=K, names=[str(i) for i in range(len(V))])


def test_background_sphere_is_seen_coloured_from_the_photos_and_faces_inwards():
    views = _sky_views()
    means, normals, colours, spacing = sphere_background(views, torch.zeros(3, dtype=torch.float64), 30.0, 4000)
    assert 0 < len(means) < 4000                           # only what the cameras see (a band around the horizon)
    assert torch.allclose(means.norm(dim=1), torch.full((len(means),), 30.0), rtol=1e-5)
    assert torch.allclose((normals * means).sum(1), -means.norm(dim=1), rtol=1e-5)
    assert means[:, 2].abs().max() < 30.0 * math.sin(math.radians(35))
    high, low = means[:, 2] > 3.0, means[:, 2] < -3.0      # well away from the horizon (seen from 3 units off)
    assert bool((colours[high, 0] > 0.99).all()) and bool((colours[high, 2] < 0.01).all())
    assert bool((colours[low, 2] > 0.99).all()) and bool((colours[low, 0] < 0.01).all())
    assert spacing[0].item() == pytest.approx(30.0 * math.sqrt(4 * math.pi / 4000), rel=1e-6)


def test_depth_range_brackets_the_points_and_the_background():
    views = _sky_views()
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(500, 3, generator=g) - 0.5            # a unit cube about the origin, cameras 3 away
    pts[0] = torch.tensor([2.0, 0.0, 0.0])                 # one point 1 unit in front of the camera at (3, 0, 0)
    near, far = depth_range(pts, views, torch.zeros(3), far_radius=20.0)
    assert near == pytest.approx(0.5, rel=1e-5)            # half the smallest depth
    assert far >= 2 * (3.0 + 20.0) - 1e-6
    pts[1] = torch.tensor([3.0 - 1e-4, 0.0, 0.0])          # a stray point on that camera's centre, 1e-4 in front
    assert depth_range(pts, views, torch.zeros(3), far_radius=20.0)[0] == pytest.approx(0.5e-4, rel=1e-2)
    assert depth_range(pts, views, torch.zeros(3), far_radius=20.0, min_depth=0.03)[0] == pytest.approx(0.5, rel=1e-5)


def test_fit_sphere_recovers_a_noisy_partial_sphere():
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=torch.float64), dim=1)
    d = d[d[:, 2] < 0.3]                                   # a cap is missing, as behind a scene's cameras
    centre = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    pts = centre + 5.0 * d + 0.01 * torch.randn(len(d), 3, generator=g, dtype=torch.float64)
    c, r = fit_sphere(pts)
    assert torch.allclose(c, centre, atol=0.01) and r == pytest.approx(5.0, abs=0.01)


def test_fill_points_are_in_the_box_seen_by_enough_views_and_coloured_from_the_photos():
    views = _sky_views()                                   # 12 cameras on a ring of radius 3, 60° field of view
    lo, hi = torch.full((3,), -2.0, dtype=torch.float64), torch.full((3,), 2.0, dtype=torch.float64)
    means, normals, colours = fill_points(lo, hi, views, 500, 1.0, torch.Generator().manual_seed(0))
    assert means.shape == normals.shape == colours.shape == (500, 3)
    assert bool(((means >= -2.0) & (means <= 2.0)).all())
    _, _, inside = project(means, views)
    assert bool(inside.all())                              # min_seen 1: every view sees every point
    assert torch.allclose(normals.norm(dim=1), torch.ones(500), atol=1e-5)
    # the cameras sit at height 0 looking level: a point above the horizon lands in the red top half
    high, low = means[:, 2] > 0.1, means[:, 2] < -0.1
    assert bool((colours[high, 0] > 0.99).all()) and bool((colours[high, 2] < 0.01).all())
    assert bool((colours[low, 2] > 0.99).all()) and bool((colours[low, 0] < 0.01).all())
    # a looser carve reaches farther out (points near a camera or beside the ring); fewer views see them
    loose, _, _ = fill_points(lo, hi, views, 500, 0.25, torch.Generator().manual_seed(0))
    _, _, seen = project(loose, views)
    assert bool((seen.float().mean(0) >= 0.25 - 1e-6).all()) and not bool(seen.all())
    again, _, _ = fill_points(lo, hi, views, 500, 1.0, torch.Generator().manual_seed(0))
    assert torch.equal(again, means)                       # seeded


def test_fill_box_grows_by_the_margin_and_an_unseen_box_is_a_clear_error():
    xyz = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 4.0]])
    lo, hi = fill_box(xyz, 0.5)
    assert lo.tolist() == [-0.5, -1.0, -2.0] and hi.tolist() == [1.5, 3.0, 6.0]
    views = _sky_views()
    far = torch.tensor([0.0, 0.0, 50.0], dtype=torch.float64)   # straight above the ring: in no view
    with pytest.raises(ValueError, match=r"only 0 of 10 random points in the box .* are seen by 80% of the 12"):
        fill_points(far, far + 1.0, views, 10, 0.8, torch.Generator().manual_seed(0), rounds=3)
    with pytest.raises(ValueError, match="min_seen"):
        fill_points(-far, far, views, 10, 0.0, torch.Generator().manual_seed(0))

"""Point-based depth fusion (nsplat.data.fusion) against exact geometry.

Depth maps are ray-traced (nsplat.data.raytrace: the synthetic room of nsplat.tasks.refine.room, a sphere, planes) or
written analytically, so every valid pixel's vertex lies exactly on a known surface; the fused surfels are checked
against the analytic surfaces (distance to the room's rectangles and boxes), the ray-traced normals, and
independently computed confidence weights.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from nsplat.cameras import intrinsics_from_fov
from nsplat.data.fusion import RADIAL_SIGMA, FusionConfig, SurfelMap, Surfels, frame_vertices, fuse, fuse_frames
from nsplat.data.raytrace import Box, Material, Plane, Sphere, camera_rays, intersect
from nsplat.tasks.refine.room import room_primitives, trajectory

F64 = torch.float64
#: The room's depth maps are 48×36 (f ≈ 31 px): a surface inclined more than ~43° to the image plane changes depth by
#: more than the default 3 % per pixel there and would count as a discontinuity; 6 % keeps the floor and walls.
ROOM_EDGE = 0.06


def _ray_trace(prims, viewmats: torch.Tensor, K: torch.Tensor, width: int, height: int):
    """Per camera the z-depth map ``[H,W]`` (ray distance times the ray's cosine to the optical axis), and all
    hit points ``[M,3]`` and their (camera-facing) normals ``[M,3]`` in world space."""
    depths, points, normals = [], [], []
    for V in viewmats:
        o, d = camera_rays(V, K, width, height)
        hit = intersect(o, d, prims)
        assert bool(torch.isfinite(hit.t).all()), "every ray must hit a surface"
        depths.append((hit.t * (d @ V[2, :3])).reshape(height, width))
        points.append(o + d * hit.t[:, None])
        normals.append(hit.normal)
    return torch.stack(depths), torch.cat(points), torch.cat(normals)


def _plane_axes(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The tangent axes of a raytrace.Plane (its documented convention: u = normalize(up × n), v = n × u)."""
    up = torch.tensor([0.0, 0.0, 1.0] if abs(float(n[2])) < 0.99 else [1.0, 0.0, 0.0], dtype=F64)
    u = torch.linalg.cross(up, n)
    u = u / u.norm()
    return u, torch.linalg.cross(n, u)


def _surface_distance(p: torch.Tensor, prims) -> torch.Tensor:
    """Unsigned distance of points ``[M,3]`` to the nearest surface of rectangles and z-rotated boxes."""
    best = torch.full((p.shape[0],), math.inf, dtype=F64)
    for pr in prims:
        c = torch.tensor(pr.centre, dtype=F64)
        if isinstance(pr, Plane):
            n = torch.tensor(pr.normal, dtype=F64)
            n = n / n.norm()
            u, v = _plane_axes(n)
            loc = p - c
            a, b, h = loc @ u, loc @ v, loc @ n
            d = torch.sqrt((a.abs() - pr.half[0]).clamp_min(0) ** 2 + (b.abs() - pr.half[1]).clamp_min(0) ** 2 + h * h)
        elif isinstance(pr, Box):
            cy, sy = math.cos(pr.yaw), math.sin(pr.yaw)
            R = torch.tensor([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]], dtype=F64)  # local → world
            q = ((p - c) @ R).abs() - torch.tensor(pr.half, dtype=F64)
            m = q.max(-1).values
            d = torch.where(m > 0, q.clamp_min(0).norm(dim=-1), -m)
        else:
            raise TypeError(type(pr))
        best = torch.minimum(best, d)
    return best


@pytest.fixture(scope="module")
def room():
    """Four cameras of the room's trajectory: 48×36 depth maps (fused) and a 2× finer render's hit points."""
    prims = room_primitives()
    V = trajectory(12)[[0, 4, 8, 11]]
    W, H = 48, 36
    K = intrinsics_from_fov(math.radians(75.0), W, H, dtype=F64)[0]
    depths, points, _ = _ray_trace(prims, V, K, W, H)
    Kf = intrinsics_from_fov(math.radians(75.0), 2 * W, 2 * H, dtype=F64)[0]
    _, fine_points, fine_normals = _ray_trace(prims, V, Kf, 2 * W, 2 * H)
    g = torch.Generator().manual_seed(0)
    return {"prims": prims, "depths": depths.float(), "images": torch.rand(len(V), H, W, 3, generator=g),
            "Ks": K.float().expand(len(V), 3, 3).clone(), "c2w": torch.linalg.inv(V), "points": points,
            "fine_points": fine_points, "fine_normals": fine_normals}


def test_surface_distance_helper_is_zero_on_ray_traced_hits(room):
    """The analytic distance used below is 0 on every ray-traced hit point and positive off the surfaces."""
    assert float(_surface_distance(room["fine_points"], room["prims"]).max()) < 1e-9
    centre = torch.tensor([[2.0, 1.75, 1.8]], dtype=F64)  # mid-air above the table
    assert float(_surface_distance(centre, room["prims"])[0]) > 0.5


@pytest.mark.parametrize("voxel", [0.02, 0.05])
def test_fused_room_surfels_lie_on_the_surfaces(room, voxel):
    """Every fused surfel of the ray-traced room lies within the voxel diagonal of the analytic surfaces (a
    confidence-weighted mean of surface points of one voxel cannot be farther), and nearly all lie on them to float
    precision (a vertex off its pixel centre by a twentieth of a pixel, or a wrong pose, moves them by millimetres)."""
    s = fuse(room["depths"], room["images"], room["Ks"], room["c2w"], FusionConfig(voxel=voxel, edge=ROOM_EDGE),
             progress=False)
    assert isinstance(s, Surfels) and s.voxel == voxel
    assert 1000 < s.means.shape[0] < room["points"].shape[0]
    d = _surface_distance(s.means.double(), room["prims"])
    assert float(d.max()) <= math.sqrt(3.0) * voxel
    assert float((d < 1e-5).double().mean()) > 0.98, float(d.quantile(0.98))
    # surfels cover what the cameras saw: each fine hit point has a surfel within a few pixel footprints
    gap, _ = cKDTree(s.means.double().numpy()).query(room["fine_points"].numpy())
    assert np.quantile(gap, 0.9) < 2 * voxel + 0.1


def test_fused_room_normals_agree_with_the_surfaces(room):
    """Fused normals match the ray tracer's camera-facing surface normal at the nearest hit point of a 2× finer
    render: median angle below 1°, 90 % below 5° (flipped, unrotated or camera-space normals are far off)."""
    s = fuse(room["depths"], room["images"], room["Ks"], room["c2w"], FusionConfig(voxel=0.03, edge=ROOM_EDGE),
             progress=False)
    assert torch.allclose(s.normals.norm(dim=-1), torch.ones(s.normals.shape[0]), atol=1e-5)
    _, j = cKDTree(room["fine_points"].numpy()).query(s.means.double().numpy())
    cos = (s.normals.double() * room["fine_normals"][torch.from_numpy(j)]).sum(-1).clamp(-1, 1)
    ang = torch.rad2deg(torch.acos(cos))
    assert float(ang.median()) < 1.0
    assert float((ang < 5.0).double().mean()) > 0.9


def test_point_cap_doubles_the_voxel(room):
    """With ``voxel = 0`` the voxel starts at the first frame's median pixel footprint and doubles whenever the map
    passes ``max_points``: the cap holds, the voxel is the start times a power of two, and half of it would not
    have met the cap (the voxel is not grown further than the cap needs); a smaller cap means a larger voxel; the
    surfels still lie on the surfaces, their scales at least ``scale_factor · voxel``."""
    cfg = FusionConfig(voxel=0.0, edge=ROOM_EDGE)
    start = float(frame_vertices(room["depths"][0], room["Ks"][0], cfg, dtype=torch.float32)["radius"].median())
    free = fuse(room["depths"], room["images"], room["Ks"], room["c2w"],
                dataclasses.replace(cfg, max_points=10 ** 6), progress=False)
    assert free.voxel == pytest.approx(start)
    voxels = []
    for budget in (600, 150):
        assert free.means.shape[0] > budget
        s = fuse(room["depths"], room["images"], room["Ks"], room["c2w"], dataclasses.replace(cfg, max_points=budget),
                 progress=False)
        assert s.means.shape[0] <= budget
        k = math.log2(s.voxel / start)
        assert k >= 1 and k == pytest.approx(round(k), abs=1e-9)
        finer = fuse(room["depths"], room["images"], room["Ks"], room["c2w"],
                     FusionConfig(voxel=s.voxel / 2, max_points=10 ** 6, edge=ROOM_EDGE), progress=False)
        assert finer.means.shape[0] > budget
        assert float(_surface_distance(s.means.double(), room["prims"]).max()) <= math.sqrt(3.0) * s.voxel
        assert float(s.scales.min()) >= cfg.scale_factor * s.voxel * (1 - 1e-6)
        voxels.append(s.voxel)
    assert voxels[1] > voxels[0]


def test_doubling_rebins_exactly(room):
    """A map that doubled its voxel from v to 2v (the cap passed at the last frame) holds the surfels of fusing on
    the 2v grid from the start: the same voxels, means, normals, colours and radii to float32 precision; frame
    counts are a lower bound (the largest of the merged voxels')."""
    v = 0.02
    order = [0, 1, 2, 3, 0]
    args = [room[k][order] for k in ("depths", "images", "Ks", "c2w")]
    direct = fuse(*args, FusionConfig(voxel=2 * v, max_points=10 ** 6, edge=ROOM_EDGE), progress=False)
    fmap = SurfelMap(FusionConfig(voxel=v, max_points=10 ** 6, edge=ROOM_EDGE))
    for b in range(4):
        fmap.add(*(a[b] for a in args))
    assert len(fmap) > direct.means.shape[0]
    fmap.cfg = dataclasses.replace(fmap.cfg, max_points=direct.means.shape[0])  # the next add passes it once
    fmap.add(*(a[4] for a in args))
    assert fmap.doublings == 1 and fmap.voxel == 2 * v
    s = fmap.surfels()
    order_s, order_d = _by_voxel(s), _by_voxel(direct)
    assert torch.equal(order_s[0], order_d[0])
    i, j = order_s[1], order_d[1]
    assert torch.allclose(s.means[i], direct.means[j], atol=1e-5, rtol=0)
    assert torch.allclose(s.normals[i], direct.normals[j], atol=1e-5)
    assert torch.allclose(s.colours[i], direct.colours[j], atol=1e-5)
    assert torch.allclose(s.scales[i], direct.scales[j], rtol=1e-5)
    assert bool((s.frames[i] <= direct.frames[j]).all() and (s.frames[i] >= 1).all())


def _by_voxel(s: Surfels) -> tuple[torch.Tensor, torch.Tensor]:
    """The surfels' voxels (each mean lies inside its voxel: a convex combination of its points) as sorted keys
    ``[N]`` and the order ``[N]`` that sorts them."""
    q = torch.floor(s.means.double() / s.voxel).long()
    key = ((q[:, 0] + 4096) * 8192 + q[:, 1] + 4096) * 8192 + q[:, 2] + 4096
    key, order = torch.sort(key)
    return key, order


def _batch_fuse(depths, images, Ks, c2w, cfg: FusionConfig, origin: str) -> dict[str, torch.Tensor]:
    """The fusion as it was before it streamed (all frames' candidates in float64, one merge): ``origin = "zero"``
    puts the voxel grid at the world origin as the map does, ``"min"`` at the candidates' minimum as before."""
    names = ("points", "normals", "colours", "radius", "weight", "frame")
    parts: dict[str, list[torch.Tensor]] = {k: [] for k in names}
    for b in range(depths.shape[0]):
        c = frame_vertices(depths[b], Ks[b], cfg)
        R, t = c2w[b, :3, :3].double(), c2w[b, :3, 3].double()
        parts["points"].append(c["points"] @ R.T + t)
        parts["normals"].append(c["normals"] @ R.T)
        parts["colours"].append(images[b].reshape(-1, images.shape[-1])[c["index"]].double())
        parts["radius"].append(c["radius"])
        parts["weight"].append(c["weight"])
        parts["frame"].append(torch.full_like(c["radius"], b, dtype=torch.long))
    c = {k: torch.cat(v) for k, v in parts.items()}
    p = c["points"] - (c["points"].min(0).values if origin == "min" else 0.0)
    q = torch.floor(p / cfg.voxel).long()
    q -= q.min(0).values
    dims = q.max(0).values + 1
    _, inv = torch.unique((q[:, 0] * dims[1] + q[:, 1]) * dims[2] + q[:, 2], return_inverse=True)
    V = int(inv.max()) + 1
    w = c["weight"]
    wsum = torch.zeros(V, dtype=F64).index_add_(0, inv, w)

    def mean(x: torch.Tensor) -> torch.Tensor:
        wx = x * w.reshape(-1, *[1] * (x.dim() - 1))
        return torch.zeros(V, *x.shape[1:], dtype=F64).index_add_(0, inv, wx) / wsum.reshape(-1, *[1] * (x.dim() - 1))

    seen = torch.zeros(V, depths.shape[0], dtype=torch.bool)
    seen[inv, c["frame"]] = True
    return {"means": mean(c["points"]), "normals": torch.nn.functional.normalize(mean(c["normals"]), dim=-1),
            "colours": mean(c["colours"]), "radius": mean(c["radius"]), "frames": seen.sum(1)}


def test_streaming_equals_batch(room):
    """The streaming map (float32 vertices and accumulators) gives the surfels of the former all-candidates float64
    fusion on the same grid: the same voxels (but for a few points on a voxel boundary in one precision and not
    the other), means within 10 µm, normals within 0.1°, the same colours, radii and frame counts. Against the former
    grid origin (the candidates' minimum) the surfels differ only by where the voxel boundaries fall: the same count
    within 3 %, every surfel within a voxel diagonal of one of the former, and as close to the surfaces."""
    cfg = FusionConfig(voxel=0.03, max_points=10 ** 6, edge=ROOM_EDGE)
    # the room's walls lie on grid planes (x = 0, ...): moved off them, no wall straddles a voxel boundary
    shift = torch.tensor([0.0123, 0.0071, 0.0047], dtype=F64)
    c2w = room["c2w"].clone()
    c2w[:, :3, 3] += shift
    args = (room["depths"], room["images"], room["Ks"], c2w)
    s = fuse(*args, cfg, progress=False)
    ref = _batch_fuse(*args, cfg, origin="zero")
    r = Surfels(ref["means"].float(), ref["normals"].float(), ref["colours"].float(),
                (cfg.scale_factor * ref["radius"].clamp_min(cfg.voxel)).float(), ref["frames"].int(), cfg.voxel)
    ks, i = _by_voxel(s)
    kr, j = _by_voxel(r)
    common, ci, cj = np.intersect1d(ks.numpy(), kr.numpy(), return_indices=True)
    assert len(common) >= 0.995 * max(len(ks), len(kr)), (len(common), len(ks), len(kr))
    i, j = i[torch.from_numpy(ci)], j[torch.from_numpy(cj)]
    close = (s.means[i] - r.means[j]).norm(dim=-1) < 1e-5
    assert float(close.double().mean()) > 0.99  # a voxel that gained or lost a boundary point moves a little
    ang = torch.rad2deg(torch.acos((s.normals[i] * r.normals[j]).sum(-1).clamp(-1, 1)))[close]
    assert float(ang.max()) < 0.1
    assert torch.allclose(s.colours[i][close], r.colours[j][close], atol=1e-5)
    assert torch.allclose(s.scales[i][close], r.scales[j][close], rtol=1e-5)
    assert bool((s.frames[i] == r.frames[j]).double().mean() > 0.99)

    before = _batch_fuse(*args, cfg, origin="min")
    n = before["means"].shape[0]
    assert abs(s.means.shape[0] - n) <= 0.03 * n
    gap, _ = cKDTree(before["means"].numpy()).query(s.means.double().numpy())
    assert gap.max() < math.sqrt(3.0) * cfg.voxel
    d_now = _surface_distance(s.means.double() - shift, room["prims"])
    d_before = _surface_distance(before["means"] - shift, room["prims"])
    assert float(d_now.quantile(0.98)) <= float(d_before.quantile(0.98)) + 1e-5
    assert float(d_now.max()) <= math.sqrt(3.0) * cfg.voxel


def test_map_size_is_independent_of_the_frame_count(room):
    """Fusing the same four views ten times over (a long sequence revisiting a room) keeps the map at the size of
    one pass, its bytes included (memory is the map plus one frame), and the surfels unchanged but for the frame
    counts (ten times as many); a generator of frames (:func:`fuse_frames`) streams the same way."""
    cfg = FusionConfig(voxel=0.03, edge=ROOM_EDGE)
    views = list(zip(room["depths"], room["images"], room["Ks"], room["c2w"]))
    fmap = SurfelMap(cfg)
    for v in views:
        fmap.add(*v)
    once, size, nbytes = fmap.surfels(), len(fmap), fmap.nbytes
    for _ in range(9):
        for v in views:
            fmap.add(*v)
            assert len(fmap) == size and fmap.nbytes == nbytes
    ten = fmap.surfels()
    assert fmap.added == 40 and torch.equal(ten.frames, 10 * once.frames)
    assert torch.allclose(ten.means, once.means, atol=1e-5, rtol=0)
    assert torch.allclose(ten.colours, once.colours, atol=1e-5)
    streamed = fuse_frames((v for _ in range(10) for v in views), cfg, progress=False)
    assert torch.equal(streamed.means, ten.means) and torch.equal(streamed.frames, ten.frames)


def test_map_stays_under_the_cap_while_streaming(room):
    """With a cap, the map never holds more than ``max_points`` surfels after any frame, whatever the count of frames
    added: each frame shifted by a jittered translation (new voxels every time) doubles the voxel instead."""
    cfg = FusionConfig(voxel=0.01, max_points=400, edge=ROOM_EDGE)
    fmap = SurfelMap(cfg)
    g = torch.Generator().manual_seed(3)
    sizes = []
    for k in range(24):
        b = k % room["depths"].shape[0]
        pose = room["c2w"][b].clone()
        pose[:3, 3] += 0.05 * torch.randn(3, generator=g, dtype=F64)
        fmap.add(room["depths"][b], room["images"][b], room["Ks"][b], pose)
        sizes.append(len(fmap))
    assert max(sizes) <= cfg.max_points and fmap.doublings >= 2 and fmap.voxel == 0.01 * 2 ** fmap.doublings
    assert fmap.surfels().means.shape[0] == sizes[-1]


def test_surfel_map_min_frames_and_bad_frames():
    """A map read out after each frame: the frame counts grow as frames overlap, ``min_frames`` keeps only voxels
    seen that often; a frame of the wrong shape or colour channels raises ValueError."""
    W, H, f = 16, 12, 16.0
    K = _intrinsics(f, W, H)
    fmap = SurfelMap(FusionConfig(voxel=0.3, min_frames=2))
    pose = torch.eye(4, dtype=F64)
    fmap.add(torch.full((H, W), 2.0), torch.rand(H, W, 3), K, pose)
    assert len(fmap) > 0 and bool((fmap.frames == 1).all())
    with pytest.raises(ValueError, match="no valid depth"):  # nothing seen twice yet: min_frames leaves nothing
        fmap.surfels() if False else SurfelMap().surfels()
    pose = pose.clone()
    pose[0, 3] = 1.0
    fmap.add(torch.full((H, W), 2.0), torch.rand(H, W, 3), K, pose)
    s = fmap.surfels()
    assert bool((s.frames == 2).all()) and 0 < s.means.shape[0] < len(fmap)
    with pytest.raises(ValueError, match=r"expected depth \[H,W\]"):
        fmap.add(torch.full((1, H, W), 2.0), torch.rand(H, W, 3), K, pose)
    with pytest.raises(ValueError, match="colour channels"):
        fmap.add(torch.full((H, W), 2.0), torch.rand(H, W, 1), K, pose)


def _intrinsics(f: float, W: int, H: int) -> torch.Tensor:
    """Square pixels, principal point at the image centre (pixel centres at half-integers)."""
    return torch.tensor([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])


def test_no_surfels_across_a_depth_discontinuity():
    """A step from 1.0 m to 1.3 m with a 'flying pixel' column at 1.15 m between (as real sensors produce): no
    surfel lies between the two planes, the pixels next to the step are left out, and every normal is the planes'
    normal. With the edge test switched off (edge = 1) the same map does give surfels between the planes."""
    W, H = 16, 12
    depth = torch.ones(H, W)
    depth[:, 8] = 1.15
    depth[:, 9:] = 1.3
    K = _intrinsics(20.0, W, H)
    args = (depth[None], torch.rand(1, H, W, 3), K[None], torch.eye(4, dtype=F64)[None])

    c = frame_vertices(depth, K, FusionConfig())
    cols = sorted(set((c["index"] % W).tolist()))
    assert cols == [1, 2, 3, 4, 5, 6, 10, 11, 12, 13, 14]
    s = fuse(*args, FusionConfig(voxel=1e-3), progress=False)
    z = s.means[:, 2].double()
    on_a_plane = ((z - 1.0).abs() < 1e-6) | ((z - 1.3).abs() < 1e-6)
    assert bool(on_a_plane.all()), z[~on_a_plane]
    assert s.means.shape[0] == len(cols) * (H - 2)
    assert float(torch.rad2deg(torch.acos(-s.normals[:, 2].double().clamp(-1, 1))).max()) < 0.1

    loose = fuse(*args, FusionConfig(voxel=1e-3, edge=1.0), progress=False)
    zl = loose.means[:, 2].double()
    assert bool(((zl > 1.0 + 1e-3) & (zl < 1.3 - 1e-3)).any())


def _rot_y(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    return torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]],
                        dtype=F64)


def _candidates_mask(depth: torch.Tensor) -> torch.Tensor:
    """Pixels that are valid, off the image border, with all four neighbours valid (for smooth depth)."""
    ok = depth > 0
    out = torch.zeros_like(ok)
    out[1:-1, 1:-1] = ok[1:-1, 1:-1] & ok[2:, 1:-1] & ok[:-2, 1:-1] & ok[1:-1, 2:] & ok[1:-1, :-2]
    return out


def test_colours_are_confidence_weighted_means():
    """Two frames of the world plane z = 2, each observing one constant colour (red, blue), merged into a single
    voxel: frame 0 head-on over the whole image, frame 1 rotated 20° about y with depth only in its right six
    columns (far from the image centre). The fused colour, position and normal are the confidence-weighted means,
    with the weights computed here from their definition (Keller's radial weight exp(−γ²/(2·0.6²)), γ the distance
    to the image centre over the half-diagonal, times |cos| between the plane normal and the viewing ray) over
    every pixel with valid neighbours, not the plain mean nor a mean without either factor."""
    W, H, f = 16, 12, 20.0
    K = _intrinsics(f, W, H).double()
    u, v = torch.meshgrid(torch.arange(W, dtype=F64) + 0.5, torch.arange(H, dtype=F64) + 0.5, indexing="xy")
    rays = torch.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, torch.ones_like(u)], -1)
    c2w = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    c2w[1, :3, :3] = _rot_y(20.0)
    radial = torch.exp(-((u - W / 2) ** 2 + (v - H / 2) ** 2) / (0.25 * (W * W + H * H)) / (2 * RADIAL_SIGMA ** 2))
    depths, sums, wpts, plain = [], [], [], []
    for b in range(2):
        n_cam = c2w[b, :3, :3].T @ torch.tensor([0.0, 0.0, 1.0], dtype=F64)  # the plane z = 2 in camera b
        z = 2.0 / (rays @ n_cam)
        if b == 1:
            z[:, :W - 6] = 0.0
        depths.append(z)
        cand = _candidates_mask(z)
        cos = (rays @ n_cam).abs() / rays.norm(dim=-1)
        w = (radial * cos)[cand]
        sums.append(w.sum())
        plain.append((cos[cand].sum(), radial[cand].sum(), cand.sum()))
        world = (rays * z[..., None])[cand] @ c2w[b, :3, :3].T
        wpts.append((world * w[:, None]).sum(0))
    images = torch.zeros(2, H, W, 3)
    images[0, ..., 0] = 1.0
    images[1, ..., 2] = 1.0
    shift = torch.tensor([10.0, 10.0, 0.0], dtype=F64)  # the voxel grid starts at the origin: one voxel holds all
    c2w[:, :3, 3] = shift
    s = fuse(torch.stack(depths).float(), images, K.float().expand(2, 3, 3), c2w, FusionConfig(voxel=100.0),
             progress=False)
    assert s.means.shape[0] == 1 and int(s.frames[0]) == 2
    share = float(sums[1] / (sums[0] + sums[1]))
    for other in zip(*plain):  # weighting by |cos| only, by the radial weight only, or by nothing differs
        assert abs(share - float(other[1] / (other[0] + other[1]))) > 0.01
    assert torch.allclose(s.colours[0].double(), torch.tensor([1 - share, 0.0, share], dtype=F64), atol=1e-5), \
        (s.colours[0], share)
    assert torch.allclose(s.means[0].double(), (wpts[0] + wpts[1]) / (sums[0] + sums[1]) + shift, atol=1e-5)
    assert torch.allclose(s.normals[0].double(), torch.tensor([0.0, 0.0, -1.0], dtype=F64), atol=1e-5)


def test_grazing_pixels_are_left_out():
    """With the edge test out of the way (edge = 100), exactly the pixels whose |cos| between the (exact, planar)
    normal and the viewing ray is at least ``grazing`` become candidates, on a plane seen at 75°."""
    W, H, f = 16, 12, 40.0
    K = _intrinsics(f, W, H).double()
    u, v = torch.meshgrid(torch.arange(W, dtype=F64) + 0.5, torch.arange(H, dtype=F64) + 0.5, indexing="xy")
    rays = torch.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, torch.ones_like(u)], -1)
    a = math.radians(75.0)
    n = torch.tensor([math.sin(a), 0.0, -math.cos(a)], dtype=F64)  # plane n·X = -1, facing the camera
    z = -1.0 / (rays @ n)
    assert bool((z > 0).all())
    cos = (rays @ n).abs() / rays.norm(dim=-1)
    for grazing in (0.2, 0.3):
        expected = _candidates_mask(z) & (cos >= grazing)
        assert 0 < int(expected.sum()) < int(_candidates_mask(z).sum())
        assert float((cos - grazing).abs().min()) > 1e-4  # no pixel on the threshold
        c = frame_vertices(z.float(), K.float(), FusionConfig(edge=100.0, grazing=grazing))
        assert c["index"].tolist() == torch.nonzero(expected.reshape(-1))[:, 0].tolist()
        assert torch.allclose(c["normals"], n.expand_as(c["normals"]), atol=1e-5)  # n faces the camera


def test_single_frame_identity_pose_reproduces_camera_space_vertices():
    """One ray-traced frame (a sphere before a wall) fused with the identity pose and a voxel far below the pixel
    footprint: each surfel is the ray tracer's hit point of one pixel (the camera-space vertex through the pixel
    centre), carries that pixel's colour, and its normal is the sphere's (or wall's) normal within 1.5°."""
    W, H = 32, 24
    K = intrinsics_from_fov(math.radians(60.0), W, H, dtype=F64)[0]
    centre = torch.tensor([0.15, -0.1, 2.0], dtype=F64)
    prims = [Sphere(tuple(centre.tolist()), 0.6, Material()),
             Plane((0.0, 0.0, 3.5), (0.0, 0.0, -1.0), (5.0, 5.0), Material())]
    depth, hits, hit_normals = _ray_trace(prims, torch.eye(4, dtype=F64)[None], K, W, H)
    image = torch.rand(1, H, W, 3, generator=torch.Generator().manual_seed(1))

    c = frame_vertices(depth[0].float(), K.float(), FusionConfig())
    assert c["points"].shape[0] > 0.5 * W * H
    assert torch.allclose(c["points"], hits[c["index"]], atol=2e-6, rtol=0)

    s = fuse(depth.float(), image, K.float()[None], torch.eye(4, dtype=F64)[None], FusionConfig(voxel=1e-4),
             progress=False)
    assert s.means.shape[0] == c["points"].shape[0]
    dist, j = cKDTree(hits.numpy()).query(s.means.double().numpy())
    assert dist.max() < 2e-6
    assert len(set(j.tolist())) == len(j)  # one surfel per pixel
    j = torch.from_numpy(j)
    assert torch.allclose(s.colours, image.reshape(-1, 3)[j], atol=1e-6, rtol=0)  # (w·c)/w in float32
    assert bool((s.frames == 1).all())
    ang = torch.rad2deg(torch.acos((s.normals.double() * hit_normals[j]).sum(-1).clamp(-1, 1)))
    assert float(ang.max()) < 1.5, float(ang.max())


def test_pixel_stride_samples_and_footprint():
    """``pixel_stride = s`` keeps every s-th pixel along rows and columns, and each sample's radius is the footprint
    of the s × s pixels it stands for, ``s · z / (f · |cos|)``: the surfel scale relative to the sample spacing
    does not depend on the stride (no holes between surfels of a strided fusion)."""
    W, H, f, z = 32, 24, 40.0, 2.0
    depth = torch.full((1, H, W), z)
    K = _intrinsics(f, W, H)
    ratios = []
    for stride in (1, 2, 4):
        cfg = FusionConfig(voxel=1e-4, pixel_stride=stride)
        idx = frame_vertices(depth[0], K, cfg)["index"]
        rows, cols = idx // W, idx % W
        assert bool((rows % stride == 0).all() and (cols % stride == 0).all())
        assert idx.numel() == len(range(stride, H - 1, stride)) * len(range(stride, W - 1, stride))
        s = fuse(depth, torch.rand(1, H, W, 3), K[None], torch.eye(4, dtype=F64)[None], cfg, progress=False)
        cos = z / s.means.double().norm(dim=-1)  # fronto-parallel plane: |cos| = z / distance
        assert torch.allclose(s.scales.double(), cfg.scale_factor * stride * z / (f * cos), rtol=1e-5)
        spacing = stride * z / f
        ratios.append(float((s.scales.double() * cos).max()) / spacing)
    assert ratios == pytest.approx([cfg.scale_factor] * 3, rel=1e-5)


def test_min_frames_drops_voxels_seen_by_fewer_frames():
    """``min_frames = 2`` keeps only the voxels both frames saw: two head-on views of the plane z = 2, the second
    shifted sideways by half the view, overlap on the middle; ``frames`` counts the observing frames."""
    W, H, f = 16, 12, 16.0
    depth = torch.full((2, H, W), 2.0)
    c2w = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    c2w[1, 0, 3] = 1.0  # the view is 2 m wide at 2 m
    args = (depth, torch.rand(2, H, W, 3), _intrinsics(f, W, H).expand(2, 3, 3), c2w)
    every = fuse(*args, FusionConfig(voxel=0.3), progress=False)
    both = fuse(*args, FusionConfig(voxel=0.3, min_frames=2), progress=False)
    assert set(every.frames.tolist()) == {1, 2}
    assert bool((both.frames == 2).all()) and 0 < both.means.shape[0] < every.means.shape[0]
    x = both.means[:, 0]
    assert float(x.min()) > 0.125 - 0.3 and float(x.max()) < 0.875 + 0.3  # the overlap of the interiors


@pytest.mark.parametrize("bad", ["depth_2d", "images_size", "Ks_shape", "c2w_shape", "batch"])
def test_invalid_shapes_raise(bad):
    """Mismatched or wrongly shaped inputs raise ValueError naming the expected shapes; so does a batch with no
    valid depth pixel."""
    B, H, W = 2, 12, 16
    depths, images = torch.full((B, H, W), 2.0), torch.rand(B, H, W, 3)
    Ks, c2w = _intrinsics(16.0, W, H).expand(B, 3, 3), torch.eye(4, dtype=F64).repeat(B, 1, 1)
    if bad == "depth_2d":
        depths = depths[0]
    elif bad == "images_size":
        images = torch.rand(B, H, W + 1, 3)
    elif bad == "Ks_shape":
        Ks = Ks[:, :2]
    elif bad == "c2w_shape":
        c2w = c2w[:, :3]
    else:
        Ks = Ks[:1]
    with pytest.raises(ValueError, match=r"expected depths \[B,H,W\]"):
        fuse(depths, images, Ks, c2w, progress=False)


def test_no_valid_depth_raises():
    """Depth maps without a single valid pixel raise ValueError instead of returning an empty scene."""
    B, H, W = 1, 12, 16
    with pytest.raises(ValueError, match="no valid depth"):
        fuse(torch.zeros(B, H, W), torch.rand(B, H, W, 3), _intrinsics(16.0, W, H)[None],
             torch.eye(4, dtype=F64)[None], progress=False)

"""Readers of RGB-D sequences (nsplat.data.rgbd) on small synthetic TUM and pose-file folders written here.

Association is checked against a port of the TUM benchmark's ``associate.py``, quaternions against scipy, the
undistortion against OpenCV's distortion model written out here, and every malformed input for a one-line
:class:`nsplat.errors.DataError` naming the file or the setting.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from nsplat.data.rgbd import (
    TUM_CAMERAS,
    Camera,
    FrameFiles,
    RGBDSequence,
    camera_of,
    downscale_depth,
    folder_files,
    load_frames,
    tum_files,
)
from nsplat.data.tum_format import (
    associate,
    matrix_to_quat,
    quat_to_matrix,
    read_file_list,
    read_trajectory,
    write_trajectory,
)
from nsplat.errors import DataError

F64 = torch.float64
T0 = 1305031229.0  # TUM-like absolute stamps (float64 keeps microseconds)
W, H = 16, 12


def _ref_associate(first: list[float], second: list[float], offset: float, max_difference: float):
    """The TUM benchmark's associate.py (``associate``), on stamp lists: all candidate pairs closer than
    ``max_difference``, closest first, each stamp used once; returns ``(a, b)`` stamp pairs sorted."""
    first_keys, second_keys = list(first), list(second)
    potential = [(abs(a - (b + offset)), a, b) for a in first_keys for b in second_keys
                 if abs(a - (b + offset)) < max_difference]
    potential.sort()
    matches = []
    for _, a, b in potential:
        if a in first_keys and b in second_keys:
            first_keys.remove(a)
            second_keys.remove(b)
            matches.append((a, b))
    matches.sort()
    return matches


def _pose(stamp: float, seed: int) -> np.ndarray:
    """A camera → world pose whose translation x encodes ``stamp`` (relative to T0) for identification."""
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = [stamp - T0, 0.1 * seed, 1.0]
    return T


def _write_traj(path: Path, stamps, seed0: int) -> dict[float, np.ndarray]:
    poses = {s: _pose(s, seed0 + k) for k, s in enumerate(stamps)}
    lines = ["# trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for s, T in poses.items():
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        lines.append(f"{s:.6f} " + " ".join(f"{x:.9f}" for x in [*T[:3, 3], *q]))
    path.write_text("\n".join(lines) + "\n")
    return poses


def _colour(k: int, w: int = W, h: int = H) -> np.ndarray:
    g = np.random.default_rng(100 + k)
    return g.integers(0, 256, (h, w, 3), dtype=np.uint8)


def _depth(k: int, w: int = W, h: int = H, scale: float = 5000.0) -> np.ndarray:
    """uint16 depth: 1–3 m, a few zeros."""
    g = np.random.default_rng(200 + k)
    d = np.round(g.uniform(1.0, 3.0, (h, w)) * scale).astype(np.uint16)
    d[0, :3] = 0
    return d


def write_tum(root: Path, rgb_stamps, depth_stamps, traj_stamps, gt_stamps=None, images: bool = True,
              trajectory: str = "odometry.txt") -> dict:
    """A TUM folder: rgb.txt / depth.txt (with the benchmark's three header lines), images, a trajectory and
    optionally a ground truth. Returns the written stamps and poses."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "rgb").mkdir(exist_ok=True)
    (root / "depth").mkdir(exist_ok=True)
    for name, stamps in (("rgb", rgb_stamps), ("depth", depth_stamps)):
        lines = [f"# {name} images", "# file: 'synthetic.bag'", "# timestamp filename"]
        lines += [f"{s:.6f} {name}/{s:.6f}.png" for s in stamps]
        (root / f"{name}.txt").write_text("\n".join(lines) + "\n")
    if images:
        for k, s in enumerate(rgb_stamps):
            iio.imwrite(root / "rgb" / f"{s:.6f}.png", _colour(k))
        for k, s in enumerate(depth_stamps):
            iio.imwrite(root / "depth" / f"{s:.6f}.png", _depth(k))
    out = {"traj": _write_traj(root / trajectory, traj_stamps, 0)}
    if gt_stamps is not None:
        out["gt"] = _write_traj(root / "groundtruth.txt", gt_stamps, 1000)
    return out


def _stamps(values) -> list[float]:
    """Stamps rounded to microseconds, as the files hold them."""
    return [round(T0 + float(v), 6) for v in values]


# ---------------------------------------------------------------------------------------------- association
def test_associate_takes_closest_pairs_first_each_stamp_once():
    """A hand-made case where greedy closest-first differs from nearest-neighbour matching, the ``max_dt``
    bound (a strict one, as associate.py's), the ``offset`` and the result order (by the first list's stamp)."""
    a = np.array([0.050, 0.000, 0.010])
    b = np.array([0.0699, 0.008, 0.031])
    # 0.010–0.008 (2 ms) is taken first, so 0.000 loses 0.008; 0.050 takes 0.031 (19 ms) over 0.0699 (19.9 ms)
    assert associate(a, b, 0.02) == [(2, 1), (0, 2)]
    assert associate(a, b, 0.0185) == [(2, 1)]
    assert associate(a, b, 0.02, offset=-0.008) == [(1, 1), (2, 2), (0, 0)]  # b − 8 ms: 0.0619, 0.000, 0.023
    assert associate(a, np.array([]), 0.02) == []
    assert associate(np.array([1.0]), np.array([1.5]), 0.5) == []  # exactly max_dt apart
    assert associate(np.array([1.0]), np.array([1.5]), 0.5000001) == [(0, 0)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_associate_matches_tum_associate_py(seed):
    """On jittered random stamps (with gaps and extra stamps) the pairs equal associate.py's, with and without
    an offset."""
    g = np.random.default_rng(seed)
    a = np.sort(T0 + np.arange(60) / 30 + g.uniform(-0.008, 0.008, 60))
    keep = g.random(60) < 0.8
    b = np.sort(np.concatenate([a[keep] + g.uniform(-0.025, 0.025, int(keep.sum())), T0 + g.uniform(0, 2, 10)]))
    a, b = np.round(a, 6), np.round(b, 6)
    for offset in (0.0, 0.01):
        got = [(a[i], b[j]) for i, j in associate(a, b, 0.02, offset)]
        assert got == _ref_associate(list(a), list(b), offset, 0.02)
        assert len(got) > 30


def test_tum_files_pair_frames_with_poses_and_ground_truth(tmp_path):
    """A TUM folder with jittered RGB and depth stamps, a missing and an extra depth frame, an odometry trajectory
    (a gap: some frames have no pose within max_dt) and a 100 Hz ground truth (a gap too): the frames, their depth
    files, poses and ground-truth poses are those associate.py picks (RGB–depth, then the kept frames with the
    trajectory, then with the ground truth); frames without a pose are dropped, the order is by time."""
    g = np.random.default_rng(5)
    n = 24
    rgb = _stamps(np.arange(n) / 30 + g.uniform(-0.003, 0.003, n))
    depth = _stamps([r - T0 + g.uniform(-0.012, 0.012) for k, r in enumerate(rgb) if k != 4] + [1.5])
    depth.sort()
    traj = _stamps([r - T0 + g.uniform(-0.004, 0.004) for k, r in enumerate(rgb) if not 9 <= k <= 11])
    gt = _stamps([t for t in np.arange(-0.05, 0.65, 0.01) if not 0.45 <= t <= 0.52])
    written = write_tum(tmp_path, rgb, depth, traj, gt)
    max_dt = 0.02
    pairs = _ref_associate(rgb, depth, 0.0, max_dt)
    with_pose = dict(_ref_associate([p[0] for p in pairs], traj, 0.0, max_dt))
    kept = [p for p in pairs if p[0] in with_pose]
    with_gt = dict(_ref_associate([p[0] for p in kept], gt, 0.0, max_dt))
    kept = [p for p in kept if p[0] in with_gt]
    assert 10 < len(kept) < n - 4  # the gaps and the missing depth frame removed frames

    files = tum_files(tmp_path, "odometry.txt", "groundtruth.txt", max_dt)
    assert [float(t) for t in files.timestamps] == [p[0] for p in kept]
    assert files.color == [tmp_path / "rgb" / f"{p[0]:.6f}.png" for p in kept]
    assert files.depth == [tmp_path / "depth" / f"{p[1]:.6f}.png" for p in kept]
    exp_c2w = np.stack([written["traj"][with_pose[p[0]]] for p in kept])
    exp_gt = np.stack([written["gt"][with_gt[p[0]]] for p in kept])
    assert files.c2w.dtype == F64 and files.c2w_gt.dtype == F64
    np.testing.assert_allclose(files.c2w.numpy(), exp_c2w, atol=2e-8)
    np.testing.assert_allclose(files.c2w_gt.numpy(), exp_gt, atol=2e-8)
    assert files.camera is None
    dropped = set(rgb[9:12])  # the trajectory's gap: no pose within 26 ms
    assert not dropped & set(files.timestamps.tolist())

    # through to the pixels: each frame's depth map is its paired depth file's
    seq = load_frames(files, camera_of("fr3", [], []), depth_scale=5000.0, depth_range=(0.1, 5.0), downscale=1,
                      progress=False)
    for i, (r, d) in enumerate(kept):
        np.testing.assert_allclose(seq.depths[i].numpy(), _depth(depth.index(d)) / 5000.0, rtol=1e-6)
        np.testing.assert_allclose(seq.images[i].numpy(), _colour(rgb.index(r)) / 255.0, atol=1e-7)
    assert torch.equal(seq.c2w, files.c2w) and torch.equal(seq.c2w_gt, files.c2w_gt)
    assert seq.timestamps.tolist() == [p[0] for p in kept]

    only_traj = tum_files(tmp_path, "odometry.txt", "", max_dt)
    assert only_traj.c2w_gt is None and len(only_traj.color) == len(with_pose) > len(kept)


# ---------------------------------------------------------------------------------------------- poses
def _rotations() -> np.ndarray:
    g = np.random.default_rng(3)
    axes = g.normal(size=(6, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    near_pi = [axis * angle for axis in axes for angle in (math.pi, math.pi - 1e-7, math.pi - 1e-3)]
    special = [[math.pi, 0, 0], [0, math.pi, 0], [0, 0, math.pi], [0, 0, 0], [1e-9, 0, 0]]
    return np.concatenate([Rotation.random(40, random_state=4).as_rotvec(), near_pi, special])


def test_quaternions_match_scipy():
    """``quat_to_matrix`` equals scipy's ``Rotation.from_quat(...).as_matrix()`` (scalar-last, non-unit input
    normalised); ``matrix_to_quat`` gives scipy's quaternion up to sign with ``qw >= 0``, including rotations of
    (nearly) 180° where the trace-based formula cancels."""
    rot = Rotation.from_rotvec(_rotations())
    q = rot.as_quat()
    R = torch.from_numpy(rot.as_matrix())
    np.testing.assert_allclose(quat_to_matrix(torch.from_numpy(q * 3.0)).numpy(), rot.as_matrix(), atol=1e-12)
    mq = matrix_to_quat(R).numpy()
    assert (mq[:, 3] >= 0).all()
    np.testing.assert_allclose(np.abs((mq * q).sum(-1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(mq, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(torch.from_numpy(mq)).numpy(), rot.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(np.abs((matrix_to_quat(R.float()).numpy() * mq).sum(-1)), 1.0, atol=1e-6)


def test_trajectory_round_trip(tmp_path):
    """``write_trajectory`` → ``read_trajectory`` returns the stamps (to the microsecond) and poses (to the 1e-9
    of the file), including near-180° rotations; the file is the TUM format (``ts tx ty tz qx qy qz qw``,
    comments first), readable by a plain parser as scipy quaternions."""
    rot = Rotation.from_rotvec(_rotations())
    n = len(rot)
    c2w = torch.eye(4, dtype=F64).repeat(n, 1, 1)
    c2w[:, :3, :3] = torch.from_numpy(rot.as_matrix())
    c2w[:, :3, 3] = torch.from_numpy(np.random.default_rng(1).normal(size=(n, 3)))
    stamps = T0 + np.arange(n) * 0.0333333
    path = write_trajectory(tmp_path / "traj.txt", stamps, c2w, comment="test")
    t, T = read_trajectory(path)
    np.testing.assert_allclose(t, stamps, rtol=0, atol=1e-6)
    assert T.dtype == F64
    np.testing.assert_allclose(T.numpy(), c2w.numpy(), atol=5e-9)
    rows = np.loadtxt(path)
    assert rows.shape == (n, 8)
    np.testing.assert_allclose(Rotation.from_quat(rows[:, 4:]).as_matrix(), rot.as_matrix(), atol=5e-9)
    np.testing.assert_allclose(rows[:, 1:4], c2w[:, :3, 3].numpy(), atol=1e-9)


def test_read_file_list(tmp_path):
    """``rgb.txt``: header comments and blank lines skipped, stamps as float64, names relative to the folder."""
    p = tmp_path / "rgb.txt"
    p.write_text("# color images\n# timestamp filename\n\n1305031229.528748 rgb/a.png\n1305031229.596600 rgb/b.png\n")
    t, names = read_file_list(p)
    assert t.dtype == np.float64 and t.tolist() == [1305031229.528748, 1305031229.596600]
    assert names == ["rgb/a.png", "rgb/b.png"]


# ---------------------------------------------------------------------------------------------- frames
def _files(tmp_path: Path, colours, depths, c2w=None) -> FrameFiles:
    """FrameFiles of PNGs written from arrays (colour uint8, depth uint16 or others)."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    cp, dp = [], []
    for k, (c, d) in enumerate(zip(colours, depths)):
        cp.append(tmp_path / f"c{k}.png")
        dp.append(tmp_path / f"d{k}.png")
        iio.imwrite(cp[-1], c)
        iio.imwrite(dp[-1], d)
    n = len(cp)
    return FrameFiles(cp, dp, torch.eye(4, dtype=F64).repeat(n, 1, 1) if c2w is None else c2w, None,
                      np.arange(n, dtype=np.float64), None)


def _load(files: FrameFiles, camera: Camera | None = None, **kw) -> RGBDSequence:
    args = {"depth_scale": 5000.0, "depth_range": (0.1, 5.0), "downscale": 1, "progress": False, **kw}
    return load_frames(files, camera or Camera(20.0, 21.0, 7.3, 5.6), **args)


@pytest.mark.parametrize("scale", [5000.0, 1000.0])
def test_load_frames_depth_in_metres_and_invalid_readings(tmp_path, scale):
    """Depth PNG values are metres × ``depth_scale``; 0 and readings outside ``depth_range`` become 0; colours
    are the 8-bit values / 255; a distortion-free camera leaves both images as they are (every pixel valid)."""
    metres = np.random.default_rng(0).uniform(0.5, 4.0, (H, W))
    raw = np.round(metres * scale).astype(np.uint16)
    raw[0, 0] = 0
    raw[1, 1] = round(0.05 * scale)  # below the range
    raw[2, 2] = round(6.0 * scale)  # beyond it
    raw[3, 3] = round(4.9 * scale)  # inside, near the far end
    colours = [_colour(0), _colour(1)]
    seq = _load(_files(tmp_path, colours, [raw, raw]), depth_scale=scale)
    assert len(seq) == 2 and (seq.height, seq.width) == (H, W)
    expected = raw.astype(np.float64) / scale
    expected[(expected < 0.1) | (expected > 5.0)] = 0.0
    assert expected[0, 0] == expected[1, 1] == expected[2, 2] == 0.0 and expected[3, 3] == pytest.approx(4.9)
    np.testing.assert_allclose(seq.depths[0].numpy(), expected, rtol=1e-6, atol=0)
    assert seq.depths.dtype == torch.float32 and seq.images.dtype == torch.float32
    np.testing.assert_allclose(seq.images.numpy(), np.stack(colours) / 255.0, atol=1e-7)
    assert bool(seq.valid.all())
    assert seq.names == ["c0", "c1"]


def test_load_frames_intrinsics_convention_and_downscale(tmp_path):
    """Returned intrinsics put pixel centres at half-integers (``K[0,2] = cx + 0.5``) and scale with the downscale;
    a downscale by 2 averages 2×2 colour blocks and keeps a depth block only when all four readings are valid and
    agree within 2 % (then their mean)."""
    cam = Camera(20.0, 21.0, 7.3, 5.6)
    colour = _colour(3)
    raw = np.full((H, W), 10000, dtype=np.uint16)  # 2 m
    raw[0:2, 0:2] = [[10000, 10100], [10050, 10150]]  # agree within 1.5 %: mean 2.015 m
    raw[0:2, 2:4] = [[10000, 10500], [10000, 10000]]  # 5 % apart: invalid
    raw[2:4, 0:2] = [[0, 10000], [10000, 10000]]  # one missing reading: invalid
    raw[2:4, 2:4] = [[10000, 15000], [15000, 15000]]  # two surfaces: invalid (not 2.375 m)
    files = _files(tmp_path, [colour] * 3, [raw] * 3)
    full = _load(files, cam)
    K = torch.tensor([[20.0, 0.0, 7.8], [0.0, 21.0, 6.1], [0.0, 0.0, 1.0]])
    assert full.Ks.shape == (3, 3, 3) and torch.allclose(full.Ks, K.expand(3, 3, 3))

    half = _load(files, cam, downscale=2)
    assert half.images.shape == (3, H // 2, W // 2, 3) and half.depths.shape == (3, H // 2, W // 2)
    assert torch.allclose(half.Ks[0], torch.tensor([[10.0, 0.0, 3.9], [0.0, 10.5, 3.05], [0.0, 0.0, 1.0]]))
    blocks = colour.reshape(H // 2, 2, W // 2, 2, 3).astype(np.float64).mean((1, 3)) / 255.0
    np.testing.assert_allclose(half.images[0].numpy(), blocks, atol=1e-6)
    d = half.depths[0].numpy()
    assert d[0, 0] == pytest.approx(2.015, rel=1e-6)
    assert d[0, 1] == 0.0 and d[1, 0] == 0.0 and d[1, 1] == 0.0
    assert (d[2:, :] == pytest.approx(2.0, rel=1e-6)) and (d[:2, 2:] == pytest.approx(2.0, rel=1e-6))
    assert bool(half.valid.all()) and half.valid.shape == (3, H // 2, W // 2)


def test_downscale_depth_blocks():
    """``downscale_depth``: the block mean where all readings are valid and within 2 % of the smallest, else 0;
    ``d = 1`` returns the map unchanged."""
    z = torch.tensor([[1.0, 1.01, 2.0, 2.1, 3.0, 3.0],
                      [1.02, 1.015, 2.0, 2.0, 0.0, 3.0]])
    out = downscale_depth(z, 2)
    assert out.shape == (1, 3)
    assert out[0, 0] == pytest.approx(float(z[:, :2].mean()))
    assert out[0, 1] == 0.0 and out[0, 2] == 0.0
    assert downscale_depth(z, 1) is z


def _opencv_distort(x: np.ndarray, y: np.ndarray, k: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's (Brown–Conrady) distortion of normalised coordinates, k = (k1, k2, p1, p2, k3)."""
    k1, k2, p1, p2, k3 = k
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def test_undistortion_follows_the_opencv_model(tmp_path):
    """With a distorted camera, target pixel (i, j) of the undistorted colour image (a linear ramp, so bilinear
    sampling is exact) shows the photo at OpenCV's distorted position of that pixel's ray, ``fx·x_d + cx`` (pixel
    centres at integers); its depth is the nearest sample there (never a blend); pixels whose ray leaves the photo
    are invalid, the others valid (after a downscale, those whose whole block was); the intrinsics are the
    pinhole twin's."""
    w, h = 48, 36
    cam = Camera(40.0, 38.0, 23.2, 17.6, (0.15, -0.05, 0.01, -0.015, 0.02))
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    colour = np.stack([5 * cols, 6 * rows, np.zeros_like(cols)], -1).astype(np.uint8)  # R = 5·x, G = 6·y
    raw = (5000 + 60 * cols + 1500 * rows).astype(np.uint16)  # 1.0–12 m, a different value per pixel
    files = _files(tmp_path, [colour] * 3, [raw] * 3)
    seq = _load(files, cam, depth_range=(0.1, 20.0))
    xd, yd = _opencv_distort((cols - cam.cx) / cam.fx, (rows - cam.cy) / cam.fy, cam.distortion)
    us, vs = cam.fx * xd + cam.cx, cam.fy * yd + cam.cy  # OpenCV pixel coordinates in the photo
    assert np.abs(us - cols).max() > 1.0  # the distortion moves pixels by more than a pixel

    img = seq.images[0].double().numpy() * 255.0
    inner = (us > 0.01) & (us < w - 1.01) & (vs > 0.01) & (vs < h - 1.01)
    assert inner.sum() > 0.6 * w * h
    np.testing.assert_allclose(img[..., 0][inner] / 5.0, us[inner], atol=2e-3)
    np.testing.assert_allclose(img[..., 1][inner] / 6.0, vs[inner], atol=2e-3)

    # nearest sample: photo pixel (round(us), round(vs)) away from the ties half-way between pixel centres
    clear = inner & (np.abs(us - np.round(us)) < 0.45) & (np.abs(vs - np.round(vs)) < 0.45)
    expected = (5000 + 60 * np.round(us) + 1500 * np.round(vs)) / 5000.0
    np.testing.assert_allclose(seq.depths[0].numpy()[clear], expected[clear], rtol=1e-6)

    inside = (us > -0.49) & (us < w - 0.51) & (vs > -0.49) & (vs < h - 0.51)
    outside = (us < -0.51) | (us > w - 0.49) | (vs < -0.51) | (vs > h - 0.49)
    assert outside.sum() > 0
    valid = seq.valid[0].numpy()
    assert valid[inside].all() and not valid[outside].any()
    assert (seq.depths[0].numpy()[outside] == 0).all()
    assert torch.allclose(seq.Ks[0], torch.tensor([[40.0, 0, 23.7], [0, 38.0, 18.1], [0, 0, 1]]))

    # downscaled by 2 (a flat depth, so that blocks agree): a pixel is valid when its whole 2×2 block was
    flat = _files(tmp_path / "flat", [colour] * 3, [np.full((h, w), 10000, np.uint16)] * 3)
    half = _load(flat, cam, downscale=2)
    blocks = seq.valid[0].reshape(h // 2, 2, w // 2, 2).permute(0, 2, 1, 3).reshape(h // 2, w // 2, 4)
    assert torch.equal(half.valid[0], blocks.all(-1)) and not bool(blocks.all(-1).all())
    assert bool((half.depths[0][~half.valid[0]] == 0).all())


def test_tum_camera_presets_and_explicit_intrinsics():
    """``camera_of``: the three TUM presets (fr1's documented calibration), explicit intrinsics with and without
    distortion, and one-line errors for bad values or an unknown preset."""
    assert set(TUM_CAMERAS) == {"fr1", "fr2", "fr3"}
    fr1 = camera_of("fr1", [], [])
    assert (fr1.fx, fr1.fy, fr1.cx, fr1.cy) == (517.3, 516.5, 318.6, 255.3)
    assert fr1.distortion == (0.2624, -0.9531, -0.0054, 0.0026, 1.1633) and fr1.distorted
    assert not camera_of("fr3", [], []).distorted
    cam = camera_of("fr1", [500.0, 501.0, 320.0, 240.0], [])
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.distorted) == (500.0, 501.0, 320.0, 240.0, False)
    assert camera_of("", [500, 500, 320, 240], [0.1, 0, 0, 0, 0]).distortion == (0.1, 0.0, 0.0, 0.0, 0.0)
    with pytest.raises(DataError, match="intrinsics"):
        camera_of("fr1", [500.0, -1.0, 320.0, 240.0], [])
    with pytest.raises(DataError, match="intrinsics"):
        camera_of("fr1", [500.0, 500.0, 320.0], [])
    with pytest.raises(DataError, match="distortion"):
        camera_of("fr1", [500.0, 500.0, 320.0, 240.0], [0.1, 0.2])
    with pytest.raises(DataError, match="fr4"):
        camera_of("fr4", [], [])


def test_subset_keeps_frames_in_order(tmp_path):
    """``RGBDSequence.subset`` picks frames (every tensor and the names) in the given order."""
    c2w = torch.eye(4, dtype=F64).repeat(3, 1, 1)
    c2w[:, 0, 3] = torch.arange(3, dtype=F64)
    seq = _load(_files(tmp_path, [_colour(k) for k in range(3)], [_depth(k) for k in range(3)], c2w))
    sub = seq.subset([2, 0])
    assert sub.names == ["c2", "c0"] and len(sub) == 2
    assert torch.equal(sub.images, seq.images[[2, 0]]) and torch.equal(sub.c2w[:, 0, 3], torch.tensor([2.0, 0.0],
                                                                                                       dtype=F64))
    assert torch.equal(sub.timestamps, torch.tensor([2.0, 0.0], dtype=F64)) and sub.c2w_gt is None


# ---------------------------------------------------------------------------------------------- malformed TUM
def _good_tum(root: Path) -> None:
    rgb = _stamps(np.arange(6) / 30)
    write_tum(root, rgb, _stamps(np.arange(6) / 30 + 0.004), _stamps(np.arange(6) / 30 + 0.001),
              _stamps(np.arange(-0.02, 0.22, 0.01)))


def _set_line(path: Path, line: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[line - 1] = text
    path.write_text("\n".join(lines) + "\n")


def _first_png(root: Path, kind: str, k: int = 0) -> Path:
    return root / kind / f"{_stamps(np.arange(6) / 30 + (0.004 if kind == 'depth' else 0.0))[k]:.6f}.png"


def _p(path: Path) -> str:
    """``path`` as a regular expression matching itself."""
    return re.escape(str(path))


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2])


MALFORMED = {
    # name: (modify the good folder, load_frames overrides, expected message pattern (a regex) given the root)
    "missing rgb.txt": (lambda r: (r / "rgb.txt").unlink(), {}, lambda r: f"{_p(r / 'rgb.txt')}: no such"),
    "wrong column count": (lambda r: _set_line(r / "depth.txt", 5, "1305031229.1 depth/x.png 7"), {},
                           lambda r: f"{_p(r / 'depth.txt')}:5: expected 2 values.*got 3"),
    "non-numeric stamp": (lambda r: _set_line(r / "rgb.txt", 6, "12:30:01 rgb/x.png"), {},
                          lambda r: f"{_p(r / 'rgb.txt')}:6: expected numbers"),
    "nan stamp": (lambda r: _set_line(r / "rgb.txt", 4, "nan rgb/x.png"), {},
                  lambda r: f"{_p(r / 'rgb.txt')}:4: .*NaN"),
    "non-unit quaternion": (lambda r: _set_line(r / "odometry.txt", 5, f"{T0 + 0.1:.6f} 0 0 0 0 0 0.5 0.5"), {},
                            lambda r: f"{_p(r / 'odometry.txt')}:5: .*norm 0.7071"),
    "trajectory line too short": (lambda r: _set_line(r / "odometry.txt", 3, f"{T0:.6f} 0 0 0 0 0 1"), {},
                                  lambda r: f"{_p(r / 'odometry.txt')}:3: expected 8 values"),
    "empty trajectory": (lambda r: (r / "odometry.txt").write_text("# nothing\n"), {},
                         lambda r: f"{_p(r / 'odometry.txt')}: the trajectory file lists nothing"),
    "trajectory covers 2 frames": (lambda r: _write_traj(r / "odometry.txt", _stamps([0.0, 1 / 30, 3.0]), 0), {},
                                   lambda r: f"{_p(r / 'odometry.txt')}: the trajectory covers 2 of 6"),
    "ground truth covers 2 frames": (lambda r: _write_traj(r / "groundtruth.txt", _stamps([0.0, 0.1]), 0), {},
                                     lambda r: f"{_p(r / 'groundtruth.txt')}: the ground truth covers 2"),
    "missing trajectory": (lambda r: (r / "odometry.txt").unlink(), {},
                           lambda r: f"{_p(r / 'odometry.txt')}: no such trajectory"),
    "no rgb-depth pairs": (lambda r: write_tum(r, _stamps(np.arange(6) / 30), _stamps(np.arange(6) / 30 + 5.0),
                                               _stamps(np.arange(6) / 30), images=False), {},
                           lambda r: f"{_p(r)}: no RGB and depth frames within 0.02 s.*max_dt"),
    "listed frame missing": (lambda r: _first_png(r, "rgb", 2).unlink(), {},
                             lambda r: f"{_p(_first_png(r, 'rgb', 2))}: missing colour frame"),
    "depth frame missing": (lambda r: _first_png(r, "depth", 5).unlink(), {},
                            lambda r: f"{_p(_first_png(r, 'depth', 5))}: missing depth frame"),
    "truncated png": (lambda r: _truncate(_first_png(r, "depth", 3)), {},
                      lambda r: f"{_p(_first_png(r, 'depth', 3))}: cannot read the image"),
    "not a png": (lambda r: _first_png(r, "rgb", 0).write_bytes(b"not an image"), {},
                  lambda r: f"{_p(_first_png(r, 'rgb', 0))}: cannot read the image"),
    "8-bit depth": (lambda r: iio.imwrite(_first_png(r, "depth", 1), np.full((H, W), 200, np.uint8)), {},
                    lambda r: f"{_p(_first_png(r, 'depth', 1))}: expected a 16-bit single-channel depth"),
    "16-bit colour": (lambda r: iio.imwrite(_first_png(r, "rgb", 1), np.full((H, W), 300, np.uint16)), {},
                      lambda r: f"{_p(_first_png(r, 'rgb', 1))}: expected an 8-bit RGB"),
    "implausible depth scale": (lambda r: None, {"depth_scale": 5.0},
                                lambda r: r"depth_scale: 5.0 gives a median depth of .* m in"),
    "no depth in range": (lambda r: None, {"depth_range": (10.0, 20.0)}, lambda r: r"depth_range: no depth reading"),
    "mismatched colour size": (lambda r: iio.imwrite(_first_png(r, "rgb", 4), _colour(0, W + 2, H)), {},
                               lambda r: f"{_p(_first_png(r, 'rgb', 4))}: frames must all be {W}×{H}.*{W + 2}×{H}"),
    "mismatched depth size": (lambda r: iio.imwrite(_first_png(r, "depth", 4), _depth(0, W, H - 2)), {},
                              lambda r: f"frames must all be {W}×{H}.*depth {W}×{H - 2}"),
    "downscale does not divide": (lambda r: None, {"downscale": 5}, lambda r: "downscale: 5 does not divide"),
}


@pytest.mark.filterwarnings("ignore:The legacy `DICOM` plugin:DeprecationWarning")  # imageio tries every plugin
@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_tum_input_fails_with_one_line(tmp_path, case):
    """Each malformed TUM folder (or setting) fails with a one-line DataError naming the file (with the line
    number, counting the header comments) or the setting, and what was expected."""
    root = tmp_path / "seq"
    _good_tum(root)
    files = tum_files(root, "odometry.txt", "groundtruth.txt", 0.02)  # the folder is good before the change
    assert len(files.color) == 6
    modify, kw, pattern = MALFORMED[case]
    modify(root)
    with pytest.raises(DataError) as info:
        files = tum_files(root, "odometry.txt", "groundtruth.txt", 0.02)
        _load(files, Camera(20.0, 20.0, 7.5, 5.5), **kw)
    msg = str(info.value)
    assert "\n" not in msg
    assert re.search(pattern(root), msg), msg


def test_missing_sequence_folder(tmp_path):
    """A sequence folder that does not exist is named in the error."""
    with pytest.raises(DataError, match="nowhere: no such RGB-D sequence folder"):
        tum_files(tmp_path / "nowhere", "odometry.txt", "", 0.02)
    with pytest.raises(DataError, match="nowhere: no such RGB-D frame folder"):
        folder_files(tmp_path / "nowhere", "")


# ---------------------------------------------------------------------------------------------- folder layout
def _write_folder(root: Path, n: int = 4, K: str = "20 0 7.5\n0 21 5.5\n0 0 1\n") -> np.ndarray:
    """A 7-Scenes-style folder: frame-00000k.color.png / .depth.png (millimetres) / .pose.txt, and
    camera-intrinsics.txt. Returns the poses [n,4,4]."""
    root.mkdir(parents=True, exist_ok=True)
    poses = []
    for k in range(n):
        stem = root / f"frame-{k:06d}"
        iio.imwrite(f"{stem}.color.png", _colour(k))
        iio.imwrite(f"{stem}.depth.png", _depth(k, scale=1000.0))
        T = _pose(T0 + k, k)
        np.savetxt(f"{stem}.pose.txt", T, fmt="%.12e", delimiter="\t")
        poses.append(T)
    (root / "camera-intrinsics.txt").write_text(K)
    return np.stack(poses)


def test_folder_layout_reads_frames_poses_and_intrinsics(tmp_path):
    """The pose-file folder: frames in name order, 4×4 camera → world poses as written, the intrinsics file's
    matrix as the camera (OpenCV convention, so ``K[0,2] = cx + 0.5`` after loading), depth in millimetres."""
    poses = _write_folder(tmp_path)
    (tmp_path / "notes.txt").write_text("not a frame\n")
    files = folder_files(tmp_path, "camera-intrinsics.txt")
    assert [p.name for p in files.color] == [f"frame-{k:06d}.color.png" for k in range(4)]
    assert [p.name for p in files.depth] == [f"frame-{k:06d}.depth.png" for k in range(4)]
    np.testing.assert_allclose(files.c2w.numpy(), poses, atol=1e-12)
    assert files.c2w_gt is None and files.timestamps.tolist() == [0.0, 1.0, 2.0, 3.0]
    cam = files.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.distorted) == (20.0, 21.0, 7.5, 5.5, False)
    seq = load_frames(files, cam, depth_scale=1000.0, depth_range=(0.1, 5.0), downscale=1, progress=False)
    raw = _depth(2, scale=1000.0)
    np.testing.assert_allclose(seq.depths[2].numpy(), raw / 1000.0, rtol=1e-6)
    assert torch.allclose(seq.Ks[0], torch.tensor([[20.0, 0, 8.0], [0, 21.0, 6.0], [0, 0, 1]]))
    assert folder_files(tmp_path, "").camera is None


def _set_pose(root: Path, k: int, text: str) -> Path:
    p = root / f"frame-{k:06d}.pose.txt"
    p.write_text(text)
    return p


def _matrix_text(M: np.ndarray) -> str:
    return "\n".join(" ".join(f"{v:.9f}" for v in row) for row in M) + "\n"


def _scaled_pose() -> str:
    M = _pose(T0, 3)
    M[:3, :3] *= 1.2
    return _matrix_text(M)


def _mirrored_pose() -> str:
    M = _pose(T0, 3)
    M[:3, 0] *= -1.0  # orthonormal, determinant -1: a reflection, not a camera pose
    return _matrix_text(M)


def _bad_last_row() -> str:
    M = _pose(T0, 3)
    M[3] = [0.0, 0.0, 0.1, 1.0]
    return _matrix_text(M)


FOLDER_MALFORMED = {
    "pose with 3 rows": (lambda r: _set_pose(r, 1, "1 0 0 0\n0 1 0 0\n0 0 1 0\n"), "frame-000001.pose.txt",
                         "expected a 4×4 camera-to-world matrix, got 3 rows"),
    "pose row with 3 values": (lambda r: _set_pose(r, 1, "1 0 0 0\n0 1 0\n0 0 1 0\n0 0 0 1\n"),
                               "frame-000001.pose.txt:2", "expected 4 values"),
    "non-rigid pose": (lambda r: _set_pose(r, 2, _scaled_pose()), "frame-000002.pose.txt", "rigid"),
    "mirrored pose": (lambda r: _set_pose(r, 2, _mirrored_pose()), "frame-000002.pose.txt", "rigid"),
    "pose last row": (lambda r: _set_pose(r, 0, _bad_last_row()), "frame-000000.pose.txt", "rigid"),
    "pose with inf": (lambda r: _set_pose(r, 3, "1 0 0 -inf\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"),
                      "frame-000003.pose.txt:1", "NaN or Inf"),
    "missing depth": (lambda r: (r / "frame-000002.depth.png").unlink(), "frame-000002.depth.png",
                      "missing depth frame"),
    "missing pose": (lambda r: (r / "frame-000003.pose.txt").unlink(), "frame-000003.pose.txt", "missing pose"),
    "too few frames": (lambda r: [(r / f"frame-{k:06d}.color.png").unlink() for k in (1, 2)], "",
                       "found 2 '<frame>.color.png' images, need at least 3"),
    "intrinsics negative focal": (lambda r: (r / "camera-intrinsics.txt").write_text("-20 0 7.5\n0 21 5.5\n0 0 1\n"),
                                  "camera-intrinsics.txt", r"expected \[\[fx 0 cx\]"),
    "intrinsics last row": (lambda r: (r / "camera-intrinsics.txt").write_text("20 0 7.5\n0 21 5.5\n0 1 1\n"),
                            "camera-intrinsics.txt", r"expected \[\[fx 0 cx\]"),
    "intrinsics skew": (lambda r: (r / "camera-intrinsics.txt").write_text("20 0.5 7.5\n0 21 5.5\n0 0 1\n"),
                        "camera-intrinsics.txt", r"expected \[\[fx 0 cx\]"),
    "intrinsics 2 rows": (lambda r: (r / "camera-intrinsics.txt").write_text("20 0 7.5\n0 21 5.5\n"),
                          "camera-intrinsics.txt", "expected a 3×3 intrinsics matrix, got 2 rows"),
    "intrinsics 4 columns": (lambda r: (r / "camera-intrinsics.txt").write_text("20 0 7.5 0\n0 21 5.5\n0 0 1\n"),
                             "camera-intrinsics.txt:1", "expected 3 values"),
    "intrinsics missing": (lambda r: (r / "camera-intrinsics.txt").unlink(), "camera-intrinsics.txt",
                           "no such intrinsics file"),
}


@pytest.mark.parametrize("case", list(FOLDER_MALFORMED))
def test_malformed_folder_fails_with_one_line(tmp_path, case):
    """Malformed pose-file folders: a pose file with 3 rows or a short row, a non-rigid (scaled), mirrored
    (determinant −1) or bad-last-row matrix, an infinite entry, a missing depth or pose file, too few frames, and a
    bad, short or missing intrinsics file each fail with a one-line DataError naming the file (and line)."""
    _write_folder(tmp_path)
    folder_files(tmp_path, "camera-intrinsics.txt")  # good before the change
    modify, where, what = FOLDER_MALFORMED[case]
    modify(tmp_path)
    with pytest.raises(DataError) as info:
        folder_files(tmp_path, "camera-intrinsics.txt")
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith(f"{tmp_path / where if where else tmp_path}:"), msg
    assert re.search(what, msg), msg

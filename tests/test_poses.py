"""Camera corrections (nsplat.tasks.refine.poses): SE(3) updates, perturbations, errors, and recovery of a known
small pose perturbation by gradient descent through the renderer on a tiny scene."""
import math

import pytest
import torch

from nsplat.cameras import camera_centres, intrinsics, look_at, perturb_viewmats
from nsplat.ops import splat_dense
from nsplat.tasks.refine.poses import (
    CameraCorrection,
    align_to_reference,
    pose_errors,
    pose_report,
    relative_pose_errors,
)


def _scene():
    """A textured box corner (back wall, floor, side wall; 3 depths and orientations) of surfels."""
    s = torch.linspace(-1.0, 1.0, 13)
    a, b = torch.meshgrid(s, s, indexing="ij")
    a, b = a.reshape(-1), b.reshape(-1)
    one = torch.ones_like(a)
    back = torch.stack([a, b, one], -1)             # z = 1, faces -z
    floor = torch.stack([a, one, 0.5 * b], -1)      # y = 1, faces -y
    side = torch.stack([one, 0.5 * a, 0.5 * b], -1)  # x = 1, faces -x
    means = torch.cat([back, floor, side])
    normals = torch.cat([torch.tensor([0.0, 0.0, -1.0]).expand_as(back), torch.tensor([0.0, -1.0,
                                                                                       0.0]).expand_as(floor),
                         torch.tensor([-1.0, 0.0, 0.0]).expand_as(side)])
    p = means
    colours = torch.stack([0.5 + 0.45 * torch.sin(9 * p[:, 0] + 3 * p[:, 2]),
                           0.5 + 0.45 * torch.cos(8 * p[:, 1] - 2 * p[:, 0]),
                           0.5 + 0.4 * torch.sin(7 * (p[:, 2] - p[:, 1]))], -1)
    scales = torch.full((means.shape[0], 2), 0.1)
    scales[back.shape[0]:] = 0.06
    return means, normals.clone(), scales, torch.full((means.shape[0],), 0.95), colours


def _cameras(count: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    eye = torch.tensor([[-0.6, -0.5, -1.6], [-0.2, -0.6, -1.5], [-0.7, -0.1, -1.4]])[:count]
    target = torch.tensor([0.2, 0.3, 0.6]).expand_as(eye)
    V = look_at(eye, target, torch.tensor([0.0, -1.0, 0.0]))
    return V, intrinsics(30.0, 30.0, 16.0, 16.0, batch=count)


def test_zero_twist_is_identity_and_frozen_cameras_stay():
    V, K = _cameras()
    corr = CameraCorrection(3, learn_pose=True, learn_focal=True, frozen=[1])
    V2, K2 = corr(V, K)
    assert torch.equal(V2, V) or torch.allclose(V2, V, atol=1e-7)
    assert torch.allclose(K2, K)
    with torch.no_grad():
        corr.twist.fill_(0.05)
        corr.log_focal.fill_(math.log(1.1))
    V3, K3 = corr(V, K)
    assert torch.allclose(V3[1], V[1], atol=1e-7) and not torch.allclose(V3[0], V[0], atol=1e-3)
    assert torch.allclose(K3[:, 0, 0], 1.1 * K[:, 0, 0]) and torch.allclose(K3[:, :2, 2], K[:, :2, 2])
    assert CameraCorrection(3, learn_pose=False).twist is None  # nothing allocated unasked


def test_twist_rotates_about_camera_centre_and_translates_in_camera_frame():
    V, K = _cameras(1)
    corr = CameraCorrection(1)
    with torch.no_grad():
        corr.twist[0] = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.03, 0.0])  # pure rotation
    V2, _ = corr(V, K)
    rot, tr = pose_errors(V2, V)
    assert rot.item() == pytest.approx(math.degrees(0.03), rel=1e-5) and tr.item() < 1e-6
    with torch.no_grad():
        corr.twist[0] = torch.tensor([0.0, 0.0, 0.1, 0.0, 0.0, 0.0])  # 0.1 along the optical axis
    V3, _ = corr(V, K)
    # υ translates the world in camera coordinates: the camera centre moves by −Rᵀυ (here 0.1 back
    # along its viewing direction)
    forward = V[0, 2, :3]
    assert torch.allclose(camera_centres(V3)[0] - camera_centres(V)[0], -0.1 * forward, atol=1e-6)


def test_pivot_rotation_keeps_the_pivot_and_reparametrises_the_same_poses():
    V, K = _cameras(2)
    c = torch.tensor([[0.0, 0.0, 1.7], [0.1, -0.2, 2.3]])
    corr = CameraCorrection(2, pivots=c)
    xi = torch.tensor([[0.01, -0.02, 0.03, 0.02, -0.01, 0.015], [0.0, 0.0, 0.0, 0.0, 0.03, 0.0]])
    with torch.no_grad():
        corr.twist.copy_(xi)
    V2, _ = corr(V, K)
    # closed form T(c) exp(ξ) T(−c)
    D = CameraCorrection(2)
    with torch.no_grad():
        D.twist.copy_(xi)
    T = torch.eye(4).repeat(2, 1, 1)
    T[:, :3, 3] = c
    Ti = torch.eye(4).repeat(2, 1, 1)
    Ti[:, :3, 3] = -c
    assert torch.allclose(V2, T @ D.delta() @ Ti @ V, atol=1e-6)
    # a pure rotation about the pivot leaves the pivot's world point where the camera sees it
    world = torch.linalg.inv(V[1]) @ torch.cat([c[1], torch.ones(1)])
    assert torch.allclose((V2[1] @ world)[:3], c[1], atol=1e-6)
    assert pose_errors(V2[1:], V[1:])[0].item() == pytest.approx(math.degrees(0.03), rel=1e-4)
    with pytest.raises(ValueError, match="pivots"):
        CameraCorrection(3, pivots=c)


def test_perturbation_has_requested_size():
    V, _ = _cameras()
    P = perturb_viewmats(V, 2.0, 0.05, generator=torch.Generator().manual_seed(0))
    rot, tr = pose_errors(P, V)
    assert torch.allclose(rot, torch.full_like(rot, 2.0), atol=1e-4)
    assert torch.allclose(tr, torch.full_like(tr, 0.05), atol=1e-6)


def _cameras64(count: int) -> torch.Tensor:
    """The rig of :func:`_cameras` built in float64 (orthonormal to rounding), ``[count,4,4]``."""
    eye = torch.tensor([[-0.6, -0.5, -1.6], [-0.2, -0.6, -1.5], [-0.7, -0.1, -1.4]], dtype=torch.float64)[:count]
    target = torch.tensor([0.2, 0.3, 0.6], dtype=torch.float64).expand_as(eye)
    return look_at(eye, target, torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))


def _rigid(axis: list[float], deg: float, t: list[float]) -> torch.Tensor:
    """A world motion ``[4,4]`` float64: rotation by ``deg`` about ``axis`` then translation ``t``."""
    from kornia.geometry.liegroup import So3
    w = torch.nn.functional.normalize(torch.tensor(axis, dtype=torch.float64), dim=0) * math.radians(deg)
    W = torch.eye(4, dtype=torch.float64)
    W[:3, :3] = So3.exp(w).matrix()
    W[:3, 3] = torch.tensor(t, dtype=torch.float64)
    return W


def test_common_rigid_offset_is_removed_by_alignment_and_invisible_to_relative_errors():
    V = _cameras64(3)
    assert V.dtype == torch.float64
    W = _rigid([0.3, -1.0, 0.2], 1.5, [0.04, -0.02, 0.03])
    moved = V @ W  # the same rig seen from a world moved by W⁻¹: every camera is off by the same motion
    rot, tr = pose_errors(moved, V)
    assert float(rot.min()) == pytest.approx(1.5, abs=1e-9)  # a world rotation is a camera rotation of the same angle
    aligned, W_est = align_to_reference(moved, V)
    torch.testing.assert_close(W_est, W, atol=1e-12, rtol=0)
    rot_a, tr_a = pose_errors(aligned, V)
    assert float(rot_a.max()) < 1e-6 and float(tr_a.max()) < 1e-12
    rpe_r, rpe_t = relative_pose_errors(moved, V)
    assert rpe_r.shape == (3,) and float(rpe_r.max()) < 1e-6 and float(rpe_t.max()) < 1e-12
    report = pose_report(moved, V)
    assert report["gauge_rot_deg"] == pytest.approx(1.5, abs=1e-9)
    assert report["gauge_trans"] == pytest.approx(float(W[:3, 3].norm()), abs=1e-12)


def test_relative_pose_error_of_one_rotated_camera_is_its_rotation():
    V = _cameras64(2)
    R = _rigid([0.0, 1.0, 0.0], 2.0, [0.0, 0.0, 0.0])
    moved = V.clone()
    moved[1] = R @ V[1]  # camera 1 turned by 2° about its own optical centre
    rot, tr = relative_pose_errors(moved, V)
    assert float(rot[0]) == pytest.approx(2.0, abs=1e-9)
    # V0 V1'⁻¹ = V0 V1⁻¹ Rᵀ: the relative translation is unchanged (R fixes the origin of camera 1)
    assert float(tr[0]) < 1e-12
    # aligned errors spread the single error over both cameras: the mean offset is half the rotation
    rep = pose_report(moved, V)
    assert rep["rot_deg_aligned"] == pytest.approx(1.0, abs=1e-3)


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="frozen"):
        CameraCorrection(2, frozen=[2])
    V, K = _cameras(2)
    with pytest.raises(ValueError, match="viewmats"):
        CameraCorrection(3)(V, K, torch.tensor([0, 1, 2]))


def test_recovers_known_pose_perturbation():
    # Two cameras perturbed by 1.5 deg and 6 cm are recovered by L-BFGS on the twists alone, with
    # gradients flowing renderer -> viewmats -> Se3.exp. float64: the loss changes near the optimum
    # are below float32 resolution.
    dt = torch.float64
    means, normals, scales, opac, colours = (t.to(dt) for t in _scene())
    V, K = _cameras(2)
    V, K = V.to(dt), K.to(dt)
    W = H = 32
    ref = splat_dense(means, normals, scales, opac, colours, V, K, W, H).image
    V0 = perturb_viewmats(V, 1.5, 0.06, generator=torch.Generator().manual_seed(1))
    rot0, tr0 = pose_errors(V0, V)
    corr = CameraCorrection(2).to(dt)
    opt = torch.optim.LBFGS(corr.parameters(), lr=1.0, max_iter=60, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-12, tolerance_change=1e-14)

    def closure() -> torch.Tensor:
        opt.zero_grad()
        Vc, Kc = corr(V0, K)
        loss = ((splat_dense(means, normals, scales, opac, colours, Vc, Kc, W, H).image - ref) ** 2).mean()
        loss.backward()
        return loss

    opt.step(closure)
    rot1, tr1 = pose_errors(corr(V0, K)[0], V)
    assert torch.allclose(rot0, torch.full_like(rot0, 1.5)) and torch.allclose(tr0, torch.full_like(tr0, 0.06))
    assert rot1.max() < 0.05, rot1   # from 1.5 deg: > 30x smaller
    assert tr1.max() < 1e-3, tr1     # from 6 cm: > 60x smaller

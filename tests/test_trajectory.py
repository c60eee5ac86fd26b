"""ATE / RPE (nsplat.tasks.refine.trajectory) against the evo package and against known answers."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from evo.core import metrics as evo_metrics
from evo.core import trajectory as evo_trajectory
from scipy.spatial.transform import Rotation

from nsplat.tasks.refine.trajectory import ate, rotation_angle, rpe, umeyama_se3

B = 50


def _se3(rotvec: np.ndarray, trans: np.ndarray) -> torch.Tensor:
    """Rigid transforms ``[N,4,4]`` (float64) from rotation vectors ``[N,3]`` and translations ``[N,3]``."""
    T = np.tile(np.eye(4), (len(rotvec), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:, :3, 3] = trans
    return torch.from_numpy(T)


def _smooth_gt(n: int = B) -> torch.Tensor:
    """A smooth camera→world trajectory ``[n,4,4]``: a wobbly loop with slowly turning cameras."""
    s = np.linspace(0.0, 1.0, n)
    pos = np.stack([2.0 * np.cos(2 * np.pi * s), 1.5 * np.sin(2 * np.pi * s), 0.3 * np.sin(6 * np.pi * s)], -1)
    rv = np.stack([0.2 * np.sin(3 * s), 0.1 + 2.0 * np.pi * s, 0.15 * np.cos(5 * s)], -1)
    return _se3(rv, pos)


def _random_rigid(rng: np.random.Generator) -> torch.Tensor:
    """One random rigid transform ``[4,4]``: any rotation, translation of a few metres."""
    return _se3(Rotation.random(random_state=rng).as_rotvec()[None], rng.normal(0, 3.0, (1, 3)))[0]


def _drifting_estimate(gt: torch.Tensor, seed: int) -> torch.Tensor:
    """``G · Q_i · A_i``: the ground truth with accumulated small random motions ``A_i`` and a rigid offset ``G``."""
    rng = np.random.default_rng(seed)
    steps = _se3(rng.normal(0, math.radians(0.5), (len(gt), 3)), rng.normal(0, 0.01, (len(gt), 3)))
    acc = [torch.eye(4, dtype=torch.float64)]
    for D in steps[1:]:
        acc.append(acc[-1] @ D)
    return _random_rigid(rng) @ gt @ torch.stack(acc)


def _evo_traj(poses: torch.Tensor):
    return evo_trajectory.PoseTrajectory3D(poses_se3=list(poses.numpy()), timestamps=np.arange(len(poses), dtype=float))


def _evo_ape(est: torch.Tensor, gt: torch.Tensor, with_scale: bool = False):
    traj_ref, traj_est = _evo_traj(gt), _evo_traj(est)
    r, t, s = traj_est.align(traj_ref, correct_scale=with_scale)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    return ape.get_all_statistics(), r, t, s


def _evo_rpe(est: torch.Tensor, gt: torch.Tensor, relation, delta: int, all_pairs: bool) -> dict[str, float]:
    metric = evo_metrics.RPE(relation, delta=delta, delta_unit=evo_metrics.Unit.frames, all_pairs=all_pairs)
    metric.process_data((_evo_traj(gt), _evo_traj(est)))
    return metric.get_all_statistics()


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("with_scale", [False, True])
def test_ate_matches_evo(seed, with_scale):
    gt = _smooth_gt()
    est = _drifting_estimate(gt, seed)
    if with_scale:                                   # a monocular estimate: unknown global scale
        est[:, :3, 3] *= 0.37
    ours = ate(est, gt, with_scale=with_scale)
    ref, r, t, s = _evo_ape(est, gt, with_scale)
    for key in ("rmse", "mean", "median", "std", "min", "max"):
        assert ours[key] == pytest.approx(ref[key], rel=1e-9, abs=0.0), key
    assert ours["rmse"] > 1e-3                       # the drift is visible: the comparison is not 0 == 0
    assert ours["scale"] == pytest.approx(s, rel=1e-9)
    assert torch.allclose(ours["alignment"][:3, :3], torch.from_numpy(s * r), atol=1e-9, rtol=0)
    assert torch.allclose(ours["alignment"][:3, 3], torch.from_numpy(t), atol=1e-9, rtol=0)
    assert isinstance(ours["rmse"], float) and ours["alignment"].shape == (4, 4)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("delta, all_pairs", [(1, False), (4, True)])
def test_rpe_matches_evo(seed, delta, all_pairs):
    # our pairs are all (i, i+Δ) (TUM's evaluate_rpe.py): evo's consecutive pairs for Δ = 1, its all_pairs for Δ > 1
    gt = _smooth_gt()
    est = _drifting_estimate(gt, seed)
    ours = rpe(est, gt, delta=delta)
    rel = evo_metrics.PoseRelation
    ref_t = _evo_rpe(est, gt, rel.translation_part, delta, all_pairs)
    ref_r = _evo_rpe(est, gt, rel.rotation_angle_deg, delta, all_pairs)
    assert ours["pairs"] == B - delta
    for ours_key, ref, key in (("trans_rmse", ref_t, "rmse"), ("trans_mean", ref_t, "mean"),
                               ("trans_median", ref_t, "median"), ("trans_max", ref_t, "max"),
                               ("rot_rmse_deg", ref_r, "rmse"), ("rot_mean_deg", ref_r, "mean"),
                               ("rot_median_deg", ref_r, "median"), ("rot_max_deg", ref_r, "max")):
        assert ours[ours_key] == pytest.approx(ref[key], rel=1e-9, abs=0.0), ours_key
    assert ours["trans_rmse"] > 1e-3 and ours["rot_rmse_deg"] > 0.1


def test_alignment_recovers_known_rigid_transform():
    rng = np.random.default_rng(3)
    gt = _smooth_gt()
    T = _random_rigid(rng)
    res = ate(T @ gt, gt)                            # est = T·gt: the alignment must undo T exactly
    assert res["rmse"] < 1e-12 and res["max"] < 1e-12
    assert torch.allclose(res["alignment"], torch.linalg.inv(T), atol=1e-12, rtol=0)
    # the bare solver, on points, with and without scale
    x = torch.from_numpy(rng.normal(size=(20, 3)))
    R_true, t_true = T[:3, :3], T[:3, 3]
    R, t = umeyama_se3(x, x @ R_true.T + t_true)
    assert torch.allclose(R, R_true, atol=1e-12) and torch.allclose(t, t_true, atol=1e-12)
    R, t, s = umeyama_se3(x, 2.5 * x @ R_true.T + t_true, with_scale=True)
    assert s == pytest.approx(2.5, rel=1e-12)
    assert torch.allclose(R, R_true, atol=1e-12) and torch.allclose(t, t_true, atol=1e-12)


def test_umeyama_never_returns_a_reflection():
    x = torch.from_numpy(np.random.default_rng(4).normal(size=(30, 3)))
    y = x * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)   # a mirror image: best fit by SVD alone is det -1
    R, t = umeyama_se3(x, y)
    assert torch.det(R) == pytest.approx(1.0, abs=1e-12)
    assert torch.allclose(R.T @ R, torch.eye(3, dtype=torch.float64), atol=1e-12)
    # the proper rotation it returns is optimal: no rotation about any axis improves the residual
    cost = (x @ R.T + t - y).square().sum()
    for rv in np.eye(3) * 1e-3:
        Rp = torch.from_numpy(Rotation.from_rotvec(rv).as_matrix()) @ R
        tp = y.mean(0) - Rp @ x.mean(0)
        assert (x @ Rp.T + tp - y).square().sum() >= cost


def test_ate_invariant_to_rigid_motion_of_estimate():
    rng = np.random.default_rng(5)
    gt = _smooth_gt()
    est = _drifting_estimate(gt, 7)
    a, b = ate(est, gt), ate(_random_rigid(rng) @ est, gt)
    for key in ("rmse", "mean", "median", "std", "min", "max"):
        assert b[key] == pytest.approx(a[key], rel=1e-9), key
    # RPE needs no alignment: a rigid motion of either trajectory leaves it unchanged
    r0, r1 = rpe(est, gt), rpe(_random_rigid(rng) @ est, _random_rigid(rng) @ gt)
    for key in ("trans_rmse", "rot_rmse_deg"):
        assert r1[key] == pytest.approx(r0[key], rel=1e-9), key


def test_rpe_one_step_error():
    gt = _smooth_gt()
    k = 17
    D = _se3(np.array([[0.0, 0.02, 0.0]]), np.array([[0.03, 0.0, -0.04]]))[0]   # 0.02 rad, 5 cm
    # the estimate follows the true relative motions, except that step k → k+1 is off by D
    est = [gt[0]]
    for i in range(B - 1):
        est.append(est[-1] @ torch.linalg.inv(gt[i]) @ gt[i + 1] @ (D if i == k else torch.eye(4, dtype=torch.float64)))
    est = torch.stack(est)
    angle = math.degrees(0.02)
    res = rpe(est, gt, delta=1)
    assert res["pairs"] == B - 1
    assert res["trans_max"] == pytest.approx(0.05, rel=1e-9)
    assert res["trans_rmse"] == pytest.approx(0.05 / math.sqrt(B - 1), rel=1e-9)
    assert res["trans_mean"] == pytest.approx(0.05 / (B - 1), rel=1e-9)
    assert res["rot_max_deg"] == pytest.approx(angle, rel=1e-9)
    assert res["rot_rmse_deg"] == pytest.approx(angle / math.sqrt(B - 1), rel=1e-9)
    assert res["trans_median"] < 1e-12 and res["rot_median_deg"] < 1e-9
    # Δ = 2: the two pairs spanning step k carry the rotation error (the later one conjugated by the next step)
    res2 = rpe(est, gt, delta=2)
    assert res2["pairs"] == B - 2
    assert res2["rot_mean_deg"] == pytest.approx(2 * angle / (B - 2), rel=1e-9)
    assert res2["rot_max_deg"] == pytest.approx(angle, rel=1e-9)


def test_rotation_angle_is_accurate_near_zero_and_pi():
    angles = np.array([0.0, 1e-9, 1e-6, 0.3, 2.0, math.pi - 1e-7, math.pi])
    axis = np.array([0.48, -0.6, 0.64])
    R = torch.from_numpy(Rotation.from_rotvec(angles[:, None] * axis).as_matrix())
    got = rotation_angle(R).numpy()
    np.testing.assert_allclose(got[1:-2], angles[1:-2], rtol=1e-9)
    assert got[0] == 0.0
    np.testing.assert_allclose(got[-2:], angles[-2:], rtol=0, atol=1e-12)


def test_error_messages():
    gt = _smooth_gt(5)
    with pytest.raises(ValueError, match="est_c2w and gt_c2w"):
        ate(gt[:4], gt)
    with pytest.raises(ValueError, match=r"gt_c2w: expected shape \[B, 4, 4\]"):
        rpe(gt, gt[:, :3])
    with pytest.raises(ValueError, match=r"est_c2w: expected shape \[B, 4, 4\]"):
        ate(gt[0], gt)
    with pytest.raises(ValueError, match="est_c2w: ATE needs at least 3 poses"):
        ate(gt[:2], gt[:2])
    with pytest.raises(ValueError, match="delta"):
        rpe(gt, gt, delta=5)
    with pytest.raises(ValueError, match="delta"):
        rpe(gt, gt, delta=0)
    with pytest.raises(ValueError, match="delta"):
        rpe(gt, gt, delta=1.0)
    bad = gt.clone()
    bad[2, 0, 3] = float("nan")
    with pytest.raises(ValueError, match=r"est_c2w: non-finite values in poses \[2\]"):
        ate(bad, gt)
    with pytest.raises(ValueError, match="gt_c2w: non-finite"):
        rpe(gt, bad)
    scaled = gt.clone()
    scaled[1, :3, :3] *= 2.0
    with pytest.raises(ValueError, match=r"est_c2w: poses \[1\] are not rigid"):
        rpe(scaled, gt)
    with pytest.raises(ValueError, match="dst"):
        umeyama_se3(torch.zeros(4, 3), torch.zeros(5, 3))
    with pytest.raises(ValueError, match="src"):
        umeyama_se3(torch.zeros(4, 2), torch.zeros(4, 2))
    assert rpe(gt, gt, delta=4)["pairs"] == 1            # the largest valid delta

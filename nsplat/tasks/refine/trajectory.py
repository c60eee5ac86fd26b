"""Trajectory metrics of the TUM RGB-D benchmark: absolute trajectory error (ATE) and relative pose error (RPE).

Definitions follow Sturm et al., "A Benchmark for the Evaluation of RGB-D SLAM Systems" (IROS 2012), and its
scripts ``evaluate_ate.py`` / ``evaluate_rpe.py``; the figures agree with the ``evo`` package's ``APE`` (translation
part, after ``align``) and ``RPE`` (``delta`` in frames, consecutive pairs) to round-off (``tests/test_trajectory.py``).

Poses are camera→world matrices ``[B,4,4]`` (``P_i`` estimated, ``Q_i`` ground truth), already associated: the same
length, pose ``i`` of one belongs to pose ``i`` of the other (association by timestamp happens elsewhere).

* ATE: the estimated camera positions are aligned to the ground-truth ones by the least-squares rigid motion
  (Horn / Umeyama, no scale unless asked for, :func:`umeyama_se3`); the errors are the distances
  ``‖R p_i + t − q_i‖`` between aligned estimated and true positions, in the trajectory's units (metres for TUM).
* RPE over the frame pairs ``(i, i+Δ)``: ``E_i = (Q_i⁻¹ Q_{i+Δ})⁻¹ (P_i⁻¹ P_{i+Δ})``; the translational error is
  ``‖trans(E_i)‖`` and the rotational error the angle of ``rot(E_i)``. No alignment: RPE is invariant to a rigid
  motion of either whole trajectory.

Everything is computed in float64; the scalar results are Python floats (JSON-ready).
"""
from __future__ import annotations

import math
from typing import Any, Literal, overload

import torch

__all__ = ["ate", "rpe", "rotation_angle", "umeyama_se3"]


@overload
def umeyama_se3(src: torch.Tensor, dst: torch.Tensor,
                with_scale: Literal[False] = ...) -> tuple[torch.Tensor, torch.Tensor]: ...


@overload
def umeyama_se3(src: torch.Tensor, dst: torch.Tensor,
                with_scale: Literal[True]) -> tuple[torch.Tensor, torch.Tensor, float]: ...


def umeyama_se3(src: torch.Tensor, dst: torch.Tensor, with_scale: bool = False
                ) -> tuple[torch.Tensor, torch.Tensor] | tuple[torch.Tensor, torch.Tensor, float]:
    """Least-squares rigid (or similarity) alignment of point sets (Umeyama, PAMI 1991; Horn 1987).

    Minimises ``Σ_i ‖s R src_i + t − dst_i‖²`` over rotations ``R`` (``det R = +1``: the reflection a plain SVD
    solution may give is replaced by the best proper rotation) and translations ``t``, with ``s = 1`` unless
    ``with_scale``. For degenerate sets (all points collinear or coincident) the rotation about the line is not
    determined; one minimiser is returned, and the aligned points, hence the residuals, are the same for all.

    Args:
        src: ``[N,3]`` points to move (e.g. estimated camera positions).
        dst: ``[N,3]`` target points (e.g. ground-truth camera positions), ``N >= 1``.
        with_scale: also fit a scale ``s > 0`` (Sim(3), for monocular trajectories of unknown scale).

    Returns:
        ``(R [3,3], t [3])``, or ``(R [3,3], t [3], s)`` with ``with_scale``; float64 tensors on ``src``'s device.
    """
    if src.ndim != 2 or src.shape[-1] != 3:
        raise ValueError(f"src: expected shape [N, 3], got {list(src.shape)}")
    if dst.shape != src.shape:
        raise ValueError(f"dst: expected the shape of src {list(src.shape)}, got {list(dst.shape)}")
    if src.shape[0] < 1:
        raise ValueError("src: needs at least one point")
    x = src.to(torch.float64)
    y = dst.to(device=x.device, dtype=torch.float64)
    mean_x, mean_y = x.mean(0), y.mean(0)
    xc, yc = x - mean_x, y - mean_y
    cov = yc.T @ xc / x.shape[0]                      # Σ_xy = 1/N Σ (y_i − μ_y)(x_i − μ_x)ᵀ   (Umeyama eq. 38)
    U, d, Vh = torch.linalg.svd(cov)
    S = torch.ones(3, dtype=x.dtype, device=x.device)
    if torch.det(U) * torch.det(Vh) < 0:             # reflection: flip the least significant direction (eq. 43)
        S[-1] = -1.0
    R = U @ torch.diag(S) @ Vh                        # eq. 40
    s = 1.0
    if with_scale:
        var_x = xc.square().sum() / x.shape[0]        # σ_x², eq. 36
        s = float((d * S).sum() / var_x) if var_x > 0 else 1.0   # eq. 42
    t = mean_y - s * (R @ mean_x)                     # eq. 41
    if with_scale:
        return R, t, s
    return R, t


def rotation_angle(R: torch.Tensor) -> torch.Tensor:
    """Angles (radians, in ``[0, π]``) of rotation matrices ``R [...,3,3]``, accurate over the whole range.

    ``θ = atan2(‖R − Rᵀ‖_F / (2√2), (tr R − 1) / 2)``: sine and cosine of the angle from the antisymmetric and
    the symmetric part, so neither ``acos`` near 0 nor ``asin`` near π loses precision.
    """
    sin = (R - R.transpose(-1, -2)).flatten(-2).norm(dim=-1) / (2.0 * math.sqrt(2.0))
    cos = (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0
    return torch.atan2(sin, cos)


def _check_poses(est_c2w: torch.Tensor, gt_c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate two associated trajectories ``[B,4,4]`` and return them as float64 on ``est_c2w``'s device."""
    for name, P in (("est_c2w", est_c2w), ("gt_c2w", gt_c2w)):
        if not isinstance(P, torch.Tensor):
            raise ValueError(f"{name}: expected a tensor [B, 4, 4], got {type(P).__name__}")
        if P.ndim != 3 or tuple(P.shape[1:]) != (4, 4):
            raise ValueError(f"{name}: expected shape [B, 4, 4], got {list(P.shape)}")
    if est_c2w.shape[0] != gt_c2w.shape[0]:
        raise ValueError(f"est_c2w and gt_c2w: expected the same number of (associated) poses, got "
                         f"{est_c2w.shape[0]} and {gt_c2w.shape[0]}")
    P = est_c2w.detach().to(torch.float64)
    Q = gt_c2w.detach().to(device=P.device, dtype=torch.float64)
    eye = torch.eye(3, dtype=P.dtype, device=P.device)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=P.dtype, device=P.device)
    for name, M in (("est_c2w", P), ("gt_c2w", Q)):
        bad = ~torch.isfinite(M).all(dim=(1, 2))
        if bad.any():
            raise ValueError(f"{name}: non-finite values in poses {bad.nonzero().flatten().tolist()[:10]}")
        R = M[:, :3, :3]
        off = ((R.transpose(1, 2) @ R - eye).abs().amax(dim=(1, 2)) > 1e-3) | (torch.det(R) <= 0)
        off |= (M[:, 3] - bottom).abs().amax(dim=1) > 1e-6
        if off.any():
            raise ValueError(f"{name}: poses {off.nonzero().flatten().tolist()[:10]} are not rigid transforms "
                             "(rotation block not orthonormal with det +1, or bottom row not [0, 0, 0, 1])")
    return P, Q


def _stats(err: torch.Tensor) -> dict[str, float]:
    """RMSE, mean, median, population std, min and max of errors ``[M]`` (numpy's conventions)."""
    return {"rmse": float(err.square().mean().sqrt()), "mean": float(err.mean()),
            "median": float(torch.quantile(err, 0.5)), "std": float(err.std(correction=0)),
            "min": float(err.min()), "max": float(err.max())}


def ate(est_c2w: torch.Tensor, gt_c2w: torch.Tensor, with_scale: bool = False) -> dict[str, Any]:
    """Absolute trajectory error (TUM ``evaluate_ate.py``) of ``est_c2w [B,4,4]`` against ``gt_c2w [B,4,4]``.

    The camera positions (translation columns) of the estimate are aligned to the ground truth by
    :func:`umeyama_se3` (rigid; Sim(3) with ``with_scale``), and the errors are the distances between aligned
    estimated and true positions. Only positions enter; orientations are not scored.

    Args:
        est_c2w: ``[B,4,4]`` estimated camera→world poses, ``B >= 3``.
        gt_c2w: ``[B,4,4]`` ground-truth camera→world poses, associated with ``est_c2w`` pose by pose.
        with_scale: fit a scale too (monocular estimates).

    Returns:
        ``rmse``, ``mean``, ``median``, ``std`` (population), ``min``, ``max`` of the ``B`` translational errors
        (units of ``gt_c2w``; Python floats), ``scale`` (1.0 unless ``with_scale``), and ``alignment``: the
        float64 ``[4,4]`` transform ``[[s R, t], [0, 1]]`` mapping the estimate's world to the ground truth's
        (``alignment @ est_c2w`` is the aligned estimate, up to the scale of its rotation block with ``with_scale``).

    Raises:
        ValueError: shapes other than ``[B,4,4]`` or differing ``B``, ``B < 3``, non-finite or non-rigid poses.
    """
    P, Q = _check_poses(est_c2w, gt_c2w)
    if P.shape[0] < 3:
        raise ValueError(f"est_c2w: ATE needs at least 3 poses, got {P.shape[0]}")
    p, q = P[:, :3, 3], Q[:, :3, 3]
    R, t, s = umeyama_se3(p, q, with_scale=True) if with_scale else (*umeyama_se3(p, q), 1.0)
    err = (s * p @ R.T + t - q).norm(dim=-1)
    T = torch.eye(4, dtype=P.dtype, device=P.device)
    T[:3, :3] = s * R
    T[:3, 3] = t
    return {**_stats(err), "scale": float(s), "alignment": T}


def rpe(est_c2w: torch.Tensor, gt_c2w: torch.Tensor, delta: int = 1) -> dict[str, float | int]:
    """Relative pose error (TUM ``evaluate_rpe.py``, fixed frame offset) of ``est_c2w`` against ``gt_c2w``.

    For each pair ``(i, i+Δ)``, ``i = 0 … B−1−Δ``: ``E_i = (Q_i⁻¹ Q_{i+Δ})⁻¹ (P_i⁻¹ P_{i+Δ})`` with ``P`` the
    estimate and ``Q`` the ground truth (camera→world); the translational error is ``‖trans(E_i)‖`` and the
    rotational error the angle of ``rot(E_i)`` (:func:`rotation_angle`). No alignment is needed.

    Args:
        est_c2w: ``[B,4,4]`` estimated camera→world poses.
        gt_c2w: ``[B,4,4]`` ground-truth camera→world poses, associated with ``est_c2w`` pose by pose.
        delta: frame offset ``Δ``, ``1 <= Δ < B``.

    Returns:
        ``trans_rmse``, ``trans_mean``, ``trans_median``, ``trans_max`` (units of ``gt_c2w``), ``rot_rmse_deg``,
        ``rot_mean_deg``, ``rot_median_deg``, ``rot_max_deg`` (degrees) as Python floats, and ``pairs``
        (``B − Δ``, int).

    Raises:
        ValueError: shapes other than ``[B,4,4]`` or differing ``B``, ``delta`` not an int in ``[1, B)``,
        non-finite or non-rigid poses.
    """
    P, Q = _check_poses(est_c2w, gt_c2w)
    if isinstance(delta, bool) or not isinstance(delta, int):
        raise ValueError(f"delta: expected an int frame offset, got {delta!r}")
    if not 1 <= delta < P.shape[0]:
        raise ValueError(f"delta: expected 1 <= delta < B = {P.shape[0]} (number of poses), got {delta}")
    P_rel = _inv_se3(P[:-delta]) @ P[delta:]
    Q_rel = _inv_se3(Q[:-delta]) @ Q[delta:]
    E = _inv_se3(Q_rel) @ P_rel
    trans = E[:, :3, 3].norm(dim=-1)
    rot = torch.rad2deg(rotation_angle(E[:, :3, :3]))
    st, sr = _stats(trans), _stats(rot)
    return {"trans_rmse": st["rmse"], "trans_mean": st["mean"], "trans_median": st["median"],
            "trans_max": st["max"], "rot_rmse_deg": sr["rmse"], "rot_mean_deg": sr["mean"],
            "rot_median_deg": sr["median"], "rot_max_deg": sr["max"], "pairs": int(E.shape[0])}


def _inv_se3(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms ``T [...,4,4]``: ``[[Rᵀ, −Rᵀ t], [0, 1]]``."""
    Rt = T[..., :3, :3].transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3:]).squeeze(-1)
    out[..., 3, 3] = 1.0
    return out


def inject_drift(c2w: torch.Tensor, seed: int, ate_rmse: float, deg_per_m: float = 40.0) -> torch.Tensor:
    """A smoothly drifting copy of ``c2w [F,4,4]`` whose ATE RMSE against it (after the SE(3) alignment) is
    ``ate_rmse`` metres, as odometry drifts: every relative motion is followed by a small error twist whose
    direction turns slowly along the sequence (a seeded blend of two random translation directions and two rotation
    axes), its rotation ``deg_per_m`` degrees per metre of its translation; the errors accumulate, so the drift
    grows along the sequence. The size is found by bisection on the twist's scale. Returns float64 ``[F,4,4]``
    with the first pose unchanged.
    """
    from kornia.geometry.liegroup import Se3  # noqa: PLC0415 - kept local: the metrics need no kornia

    if ate_rmse <= 0:
        raise ValueError(f"ate_rmse: expected > 0 metres, got {ate_rmse}")
    P = c2w.double()
    F = P.shape[0]
    g = torch.Generator().manual_seed(seed)
    dirs = torch.nn.functional.normalize(torch.randn(4, 3, generator=g, dtype=torch.float64), dim=-1)
    s = torch.linspace(0, 1, F, dtype=torch.float64)[:, None]
    trans = torch.nn.functional.normalize((1 - s) * dirs[0] + s * dirs[1], dim=-1)
    axis = torch.nn.functional.normalize((1 - s) * dirs[2] + s * dirs[3], dim=-1)
    rel = _inv_se3(P[:-1]) @ P[1:]

    def drift(scale: float) -> torch.Tensor:
        step = scale / max(F - 1, 1)
        twist = torch.cat([trans * step, axis * math.radians(deg_per_m) * step], -1)
        E = Se3.exp(twist).matrix().detach()
        out = [P[0]]
        for i in range(F - 1):
            out.append(out[-1] @ rel[i] @ E[i + 1])
        return torch.stack(out)

    lo, hi = 0.0, 1.0
    while ate(drift(hi), P)["rmse"] < ate_rmse:
        hi *= 2.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ate(drift(mid), P)["rmse"] < ate_rmse else (lo, mid)
    return drift(0.5 * (lo + hi))

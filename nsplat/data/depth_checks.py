"""Checks that an RGB-D sequence's depth and trajectory can be trusted, run after the frames are decoded and before
any fusion or refinement (:func:`nsplat.tasks.refine.data.load_rgbd`).

* **Depth scale against the trajectory** (:func:`depth_scale_error`, :func:`check_depth_scale`): a wrong
  ``depth_scale`` multiplies every depth by one factor ``s``. Back-projecting frame A's depth and moving it into
  frame B by the trajectory's relative motion ``(R, t)`` gives ``R·sX + t``, which agrees with B's (equally
  scaled) depth only when the translation is scaled by the same ``s``: the depths are tested against the
  trajectory with its translations scaled by ``σ`` over a log grid, and the ``σ`` that makes them agree best is
  the depth's scale error (rotation alone says nothing about it, so pairs with the widest baseline are used).
  The raw median-depth check of :func:`nsplat.data.rgbd.load_frames` is the only one when the trajectory is
  estimated from the depth itself (it is then consistent with any scale).
* **A trajectory identical to the ground truth** (:func:`same_trajectory`): its ATE measures nothing.
"""
from __future__ import annotations

import torch

from nsplat.errors import DataError

#: Translation scales tested (log grid, 1/8 to 8).
SCALES = tuple(2.0 ** (k / 8) for k in range(-24, 25))
#: A point's depth residual (relative to the reading it is compared with) counts at most this much.
TRUNCATE = 0.1
#: The depth is taken as wrongly scaled when the best scale is outside ``[1/TOLERANCE, TOLERANCE]`` and its
#: score beats the trajectory's own (``σ = 1``) by the factor ``MARGIN``. On TUM fr1/rpy (rotation-dominated,
#: baselines of about 10 cm) the estimate lies within 0.7-1.4 at the right scale and at 3.7-7.3 with
#: ``depth_scale`` 1000 (5× too deep), the score ratio about 1.15 and 1.5.
TOLERANCE = 2.2
MARGIN = 1.25
#: Frame pairs compared (anchors spread over the sequence) and points sampled per anchor.
PAIRS = 8
POINTS = 3000
#: Largest viewing-direction change (degrees) between the frames of a pair (they must overlap).
MAX_ANGLE_DEG = 25.0


def _pairs(c2w: torch.Tensor, count: int) -> list[tuple[int, int]]:
    """Up to ``count`` frame pairs ``(a, b)`` of ``c2w [F,4,4]``: anchors spread over the sequence, each with the
    frame of widest baseline among those whose optical axis turned by at most :data:`MAX_ANGLE_DEG`."""
    F = c2w.shape[0]
    axes = c2w[:, :3, 2]
    centres = c2w[:, :3, 3]
    out = []
    for a in sorted({round(x) for x in torch.linspace(0, F - 1, min(count, F)).tolist()}):
        cos = (axes @ axes[a]).clamp(-1, 1)
        ok = torch.rad2deg(torch.acos(cos)) <= MAX_ANGLE_DEG
        ok[a] = False
        if not bool(ok.any()):
            continue
        base = torch.where(ok, (centres - centres[a]).norm(dim=-1), torch.full_like(cos, -1.0))
        out.append((a, int(base.argmax())))
    return out


def depth_scale_error(depths: torch.Tensor, Ks: torch.Tensor, c2w: torch.Tensor, seed: int = 0
                      ) -> tuple[float, float, float]:
    """How well frames' depths agree with the trajectory's motion as the translation is scaled.

    Args:
        depths: ``[F,H,W]`` metres, 0 where invalid.
        Ks: ``[F,3,3]`` pinhole intrinsics (pixel centres at half-integers, :mod:`nsplat.cameras`).
        c2w: ``[F,4,4]`` camera → world poses (OpenCV camera axes).
        seed: seed of the point sample.

    Returns:
        ``(best, score_best, score_one)``: the translation scale ``σ`` (from :data:`SCALES`) under which A's depth
        moved into B agrees best with B's (the depths' scale error: the depth reads ``best`` times the
        trajectory's scale), its score and the score of ``σ = 1`` (the mean over the sampled points of the
        truncated relative depth residual, :data:`TRUNCATE` for a point that leaves B's image or meets no
        reading). ``(1.0, 0.0, 0.0)`` when no pair has readings.
    """
    g = torch.Generator().manual_seed(seed)
    F, H, W = depths.shape
    P = c2w.double()
    sigma = torch.tensor(SCALES, dtype=torch.float64)
    total, count = torch.zeros_like(sigma), 0
    for a, b in _pairs(P, PAIRS):
        v, u = torch.nonzero(depths[a] > 0, as_tuple=True)
        if v.numel() == 0:
            continue
        pick = torch.randperm(v.numel(), generator=g)[:POINTS]
        v, u = v[pick], u[pick]
        z = depths[a, v, u].double()
        Ka, Kb = Ks[a].double(), Ks[b].double()
        X = torch.stack([(u + 0.5 - Ka[0, 2]) / Ka[0, 0] * z, (v + 0.5 - Ka[1, 2]) / Ka[1, 1] * z, z], -1)
        T = torch.linalg.inv(P[b]) @ P[a]
        Y = (X @ T[:3, :3].T)[None] + sigma[:, None, None] * T[:3, 3]  # [S,N,3]
        zb = Y[..., 2]
        front = zb > 1e-6
        ub = torch.floor(Kb[0, 0] * Y[..., 0] / zb.clamp_min(1e-6) + Kb[0, 2]).long()
        vb = torch.floor(Kb[1, 1] * Y[..., 1] / zb.clamp_min(1e-6) + Kb[1, 2]).long()
        inside = front & (ub >= 0) & (ub < W) & (vb >= 0) & (vb < H)
        read = depths[b][vb.clamp(0, H - 1), ub.clamp(0, W - 1)].double()
        hit = inside & (read > 0)
        seen = hit[SCALES.index(1.0)]  # points with a reading in B under the trajectory as it is
        r = torch.where(hit, ((zb - read).abs() / read.clamp_min(1e-6)).clamp(max=TRUNCATE),
                        torch.full_like(zb, TRUNCATE))
        total += (r * seen).sum(-1)
        count += int(seen.sum())
    if count == 0:
        return 1.0, 0.0, 0.0
    score = total / count
    k = int(score.argmin())
    return float(sigma[k]), float(score[k]), float(score[SCALES.index(1.0)])


def check_depth_scale(depths: torch.Tensor, Ks: torch.Tensor, c2w: torch.Tensor, depth_scale: float) -> None:
    """Raise a one-line :class:`DataError` when the depth (``[F,H,W]`` metres, read at ``depth_scale`` PNG units per
    metre) disagrees with the trajectory ``c2w [F,4,4]`` (intrinsics ``Ks [F,3,3]``) by a clear scale factor
    (:func:`depth_scale_error`)."""
    best, s_best, s_one = depth_scale_error(depths, Ks, c2w)
    if not 1.0 / TOLERANCE <= best <= TOLERANCE and s_one > MARGIN * s_best:
        how = f"{best:.2g}× too deep" if best > 1 else f"{1 / best:.2g}× too shallow"
        raise DataError(f"data.rgbd.depth_scale: {depth_scale:g} makes the depth {how} for the trajectory's motion "
                        f"(overlapping frames agree best at depth_scale ≈ {depth_scale * best:.4g}; 5000 for TUM, "
                        f"1000 for millimetres; or is the trajectory in other units than metres?)")


def same_trajectory(c2w: torch.Tensor, c2w_gt: torch.Tensor, tol: float = 1e-6) -> bool:
    """Whether the poses ``c2w [F,4,4]`` are the ground truth ``c2w_gt [F,4,4]`` up to the choice of world frame
    (every entry of the poses relative to the first frame within ``tol``): a trajectory whose ATE measures
    nothing."""
    if c2w.shape != c2w_gt.shape:
        return False
    rel = torch.linalg.inv(c2w[:1].double()) @ c2w.double()
    rel_gt = torch.linalg.inv(c2w_gt[:1].double()) @ c2w_gt.double()
    return bool(((rel - rel_gt).abs() <= tol).all())

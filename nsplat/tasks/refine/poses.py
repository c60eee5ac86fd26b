"""Learnable camera corrections: per-camera SE(3) pose updates and optional focal scaling.

A camera ``i`` with initial world→camera matrix ``V_i`` (OpenCV convention, see
:mod:`nsplat.cameras`) is corrected by a left-multiplied twist in the camera frame::

    V_i' = exp(ξ_i) · V_i,      ξ_i = (υ_i, ω_i) ∈ se(3)   (translation first, kornia's order)

so ``ω_i`` rotates the camera about its own optical centre and ``υ_i`` translates the world in the
camera's axes (the optical centre moves by ``−Rᵢ'ᵀ υ_i``); world units and radians.

Optionally the rotation acts about a *pivot* ``c_i`` given in camera coordinates (e.g. the point
at the scene's median depth on the optical axis)::

    V_i' = T(c_i) · exp(ξ_i) · T(−c_i) · V_i        (T: pure translation)

This only re-parametrises the same set of poses, but it conditions the problem: rotating the
camera about its optical centre by ω shifts the image almost like translating it by ``ω × depth``
(the two differ only through depth variation), so with a centre pivot the loss has a long, narrow
valley along which ω and υ trade off, and Adam's per-coordinate scaling cannot follow it. About a
pivot at the scene's depth, ω changes the viewing angle of the scene while υ shifts it: nearly
decoupled directions, which diagonal preconditioning handles. ``exp`` is kornia's
:class:`kornia.geometry.liegroup.Se3` exponential map; ξ starts at 0 (identity), so gradients from
the renderer reach ξ through ``viewmats``. The optional focal correction multiplies ``fx, fy`` by
``exp(φ)`` (one ``φ`` per camera, or one shared by all), reaching ``Ks`` through the op's projection.

Also here: rotation/translation pose errors, used to score refinement (random pose perturbations of a
given size, which build the benchmarks, are :func:`nsplat.cameras.perturb_viewmats`). When the scene is learnable too,
poses are only determined up
to a common rigid motion of scene and cameras (the gauge), so besides the absolute errors against the
ground truth there are two gauge-free scores: errors after removing the common rigid offset
(:func:`align_to_reference`, like the aligned trajectory error of SLAM benchmarks) and relative pose
errors over all camera pairs (:func:`relative_pose_errors`, no fitted alignment at all).
"""
from __future__ import annotations

import math

import torch
from kornia.geometry.liegroup import Se3

from nsplat.cameras import camera_centres


class CameraCorrection(torch.nn.Module):
    """Per-camera SE(3) corrections (and optionally focal scales) of ``num_cameras`` cameras.

    Only what is asked for is allocated: without ``learn_pose`` there is no twist parameter, without
    ``learn_focal`` no focal parameter.

    Args:
        num_cameras: number of cameras B.
        learn_pose: allocate the twists ``ξ [B, 6]`` (``(υ, ω)``, zeros at start).
        learn_focal: allocate log focal scales ``φ`` (``[B]``, or ``[1]`` if ``shared_focal``).
        shared_focal: one focal correction shared by all cameras (one physical lens).
        frozen: camera indices whose pose is kept fixed (e.g. an anchor frame fixing the gauge).
        pivots: ``[B, 3]`` rotation pivots in camera coordinates (``None``: the optical centres).
    """

    def __init__(self, num_cameras: int, *, learn_pose: bool = True, learn_focal: bool = False,
                 shared_focal: bool = True, frozen: list[int] | tuple[int, ...] = (),
                 pivots: torch.Tensor | None = None) -> None:
        super().__init__()
        if num_cameras < 1:
            raise ValueError(f"num_cameras must be >= 1, got {num_cameras}")
        bad = [i for i in frozen if not 0 <= int(i) < num_cameras]
        if bad:
            raise ValueError(f"frozen: camera indices {bad} out of range [0, {num_cameras})")
        self.num_cameras = num_cameras
        self.twist = torch.nn.Parameter(torch.zeros(num_cameras, 6)) if learn_pose else None
        self.log_focal = (torch.nn.Parameter(torch.zeros(1 if shared_focal else num_cameras))
                          if learn_focal else None)
        mask = torch.ones(num_cameras, 1)
        mask[list(frozen)] = 0.0
        self.register_buffer("pose_mask", mask, persistent=False)
        if pivots is not None and tuple(pivots.shape) != (num_cameras, 3):
            raise ValueError(f"pivots: expected shape [{num_cameras}, 3], got {list(pivots.shape)}")
        self.register_buffer("pivots", None if pivots is None else pivots.detach().float().clone(),
                             persistent=False)

    def delta(self, index: torch.Tensor | None = None) -> torch.Tensor:
        """Correction matrices ``exp(ξ) [b, 4, 4]`` of cameras ``index [b]`` (all if ``None``)."""
        idx = self._index(index)
        if self.twist is None:
            return torch.eye(4, device=idx.device).expand(idx.numel(), 4, 4)
        xi = self.twist[idx] * self.pose_mask[idx]
        D = Se3.exp(xi).matrix()
        if self.pivots is None:
            return D
        # T(c) · D · T(−c) = [R, t + c − R c]
        c = self.pivots[idx].to(D)
        R = D[:, :3, :3]
        t = D[:, :3, 3] + c - (R @ c[..., None])[..., 0]
        top = torch.cat([R, t[..., None]], -1)
        bottom = D[:, 3:, :]
        return torch.cat([top, bottom], 1)

    def forward(self, viewmats: torch.Tensor, Ks: torch.Tensor,
                index: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Corrected cameras.

        Args:
            viewmats: ``[b, 4, 4]`` initial world→camera matrices of cameras ``index``.
            Ks: ``[b, 3, 3]`` initial intrinsics of the same cameras.
            index: ``[b]`` long camera indices into ``0..num_cameras-1`` (``None``: all, in order).

        Returns:
            ``(viewmats' [b,4,4], Ks' [b,3,3])``, differentiable w.r.t. the corrections.
        """
        idx = self._index(index)
        if viewmats.shape != (idx.numel(), 4, 4) or Ks.shape != (idx.numel(), 3, 3):
            raise ValueError(f"viewmats {tuple(viewmats.shape)} / Ks {tuple(Ks.shape)} do not match "
                             f"{idx.numel()} camera indices (expected [b,4,4] and [b,3,3])")
        out_v = viewmats
        if self.twist is not None:
            out_v = self.delta(idx).to(viewmats) @ viewmats
        out_k = Ks
        if self.log_focal is not None:
            phi = self.log_focal if self.log_focal.numel() == 1 else self.log_focal[idx]
            s = torch.exp(phi).to(Ks).expand(idx.numel())
            focal = torch.zeros(3, 3, dtype=Ks.dtype, device=Ks.device)
            focal[0, 0] = focal[1, 1] = 1.0  # only fx and fy are scaled; cx, cy stay
            out_k = Ks + (s[:, None, None] - 1.0) * Ks * focal
        return out_v, out_k

    def _index(self, index: torch.Tensor | None) -> torch.Tensor:
        device = self.pose_mask.device
        if index is None:
            return torch.arange(self.num_cameras, device=device)
        idx = torch.as_tensor(index, device=device).long().reshape(-1)
        if idx.numel() and (idx.min() < 0 or idx.max() >= self.num_cameras):
            raise ValueError(f"camera index out of range [0, {self.num_cameras}): {idx.tolist()}")
        return idx


def odometry_prior(deltas: torch.Tensor, sigma: tuple[float, float] | list[float]) -> torch.Tensor:
    """The odometry prior of consecutive cameras' corrections ``deltas [B,4,4]`` (:meth:`CameraCorrection.delta`,
    in time order): the mean over the ``B − 1`` neighbour pairs of ``(‖Δt‖/σ_t)² + (‖ΔR‖_F/√2/σ_r)²`` (a 0-dim
    tensor; 0 for one camera; ``‖ΔR‖_F/√2`` is the angle between the two rotations for small angles).

    ``V_i' V_j'⁻¹ = D_i (V_i V_j⁻¹) D_j⁻¹``: for neighbours (a small relative motion) equal corrections keep the
    relative motion, so the difference of their corrections measures how far the corrected trajectory leaves the
    odometry's frame-to-frame motion.
    """
    if deltas.shape[0] < 2:
        return deltas.new_zeros(())
    dR = (deltas[1:, :3, :3] - deltas[:-1, :3, :3]).flatten(1).pow(2).sum(-1) / 2.0
    dt = (deltas[1:, :3, 3] - deltas[:-1, :3, 3]).pow(2).sum(-1)
    return (dt / sigma[0] ** 2 + dR / sigma[1] ** 2).mean()


def motion_prior(viewmats: torch.Tensor, times: torch.Tensor, sigma: float) -> torch.Tensor:
    """The smooth-motion prior of cameras ``viewmats [B,4,4]`` captured at ``times [B]`` (seconds, increasing): the
    mean over the ``B − 2`` inner cameras of ``(‖a_i‖/σ)²``, ``a_i`` the acceleration of the optical centres by
    divided differences, ``σ`` in m/s² (a 0-dim tensor; 0 for fewer than 3 cameras).

    A hand-held camera's centre moves smoothly between frames (TUM ``fr1_rpy``'s ground truth: 0.4 m/s² RMS at
    15 Hz, where its visual odometry jitters at 2.2 m/s²): the constant-velocity motion model of tracking, here as a
    soft term.
    """
    if viewmats.shape[0] < 3:
        return viewmats.new_zeros(())
    R, t = viewmats[:, :3, :3], viewmats[:, :3, 3]
    c = -(R.transpose(1, 2) @ t[..., None])[..., 0]
    tm = times.double().to(c.device)  # differences of absolute stamps (1.3e9 s) need float64
    v = (c[1:] - c[:-1]) / (tm[1:] - tm[:-1]).to(c.dtype)[:, None]
    a = (v[1:] - v[:-1]) / (0.5 * (tm[2:] - tm[:-2])).to(c.dtype)[:, None]
    return (a.pow(2).sum(-1) / sigma ** 2).mean()


def pose_errors(viewmats: torch.Tensor, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-camera rotation error (degrees, geodesic angle of ``R Rᵣᵀ``, from the chordal distance) and translation error
    (distance between optical centres, world units) of ``viewmats [B,4,4]`` against ``reference``.

    Returns ``(rot_deg [B], trans [B])`` (float64).
    """
    V, Vr = viewmats.detach().double(), reference.detach().double().to(viewmats.device)
    # ‖R − Rᵣ‖_F = 2√2 sin(θ/2): stable for small angles, unlike acos of the trace
    chord = (V[:, :3, :3] - Vr[:, :3, :3]).flatten(1).norm(dim=-1) / (2.0 * math.sqrt(2.0))
    rot = torch.rad2deg(2.0 * torch.asin(chord.clamp(max=1.0)))
    trans = (camera_centres(V) - camera_centres(Vr)).norm(dim=-1)
    return rot, trans


def align_to_reference(viewmats: torch.Tensor, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Remove the common rigid offset of cameras ``viewmats [B,4,4]`` relative to ``reference [B,4,4]``.

    Each camera defines a world offset ``W_i = Vᵣ_i⁻¹ V_i`` (identity when it matches its reference); the
    common offset ``W`` has the chordal mean of the ``W_i`` rotations (projection of their sum onto SO(3))
    and the mean of their translations. Returns ``(viewmats W⁻¹ [B,4,4], W [4,4])`` (float64): the cameras
    expressed in the reference's world frame, scored by :func:`pose_errors` as "aligned" errors.
    """
    V, Vr = viewmats.detach().double(), reference.detach().double().to(viewmats.device)
    Wi = torch.linalg.inv(Vr) @ V
    U, _, Vt = torch.linalg.svd(Wi[:, :3, :3].sum(0))
    if torch.det(U @ Vt) < 0:
        U = U.clone()
        U[:, -1] = -U[:, -1]
    W = torch.eye(4, dtype=V.dtype, device=V.device)
    W[:3, :3] = U @ Vt
    W[:3, 3] = Wi[:, :3, 3].mean(0)
    return V @ torch.linalg.inv(W), W


def relative_pose_errors(viewmats: torch.Tensor, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Relative pose errors over all ordered camera pairs ``i < j`` (gauge-free, no alignment).

    For each pair the relative motion ``V_i V_j⁻¹`` is compared with ``Vᵣ_i Vᵣ_j⁻¹``: the rotation error in
    degrees (as :func:`pose_errors`) and the distance between the two relative translations (world units).
    Returns ``(rot_deg [P], trans [P])`` (float64) with ``P = B(B−1)/2``; empty for ``B < 2``.
    """
    V, Vr = viewmats.detach().double(), reference.detach().double().to(viewmats.device)
    i, j = torch.triu_indices(V.shape[0], V.shape[0], offset=1, device=V.device)
    rel = V[i] @ torch.linalg.inv(V[j])
    rel_r = Vr[i] @ torch.linalg.inv(Vr[j])
    chord = (rel[:, :3, :3] - rel_r[:, :3, :3]).flatten(1).norm(dim=-1) / (2.0 * math.sqrt(2.0))
    rot = torch.rad2deg(2.0 * torch.asin(chord.clamp(max=1.0)))
    trans = (rel[:, :3, 3] - rel_r[:, :3, 3]).norm(dim=-1)
    return rot, trans


def pose_report(viewmats: torch.Tensor, reference: torch.Tensor) -> dict[str, float]:
    """Mean pose errors of ``viewmats [B,4,4]`` against ``reference [B,4,4]``: absolute (``rot_deg``,
    ``trans``, with maxima), after removing the common rigid offset (``rot_deg_aligned``,
    ``trans_aligned``, plus the offset's size ``gauge_rot_deg``/``gauge_trans``, named for the gauge
    freedom it includes when the scene is learnable) and over camera pairs (``rpe_rot_deg``,
    ``rpe_trans``)."""
    rot, tr = pose_errors(viewmats, reference)
    aligned, W = align_to_reference(viewmats, reference)
    rot_a, tr_a = pose_errors(aligned, reference)
    rpe_r, rpe_t = relative_pose_errors(viewmats, reference)
    gauge_r, _ = pose_errors(W[None], torch.eye(4, dtype=W.dtype, device=W.device)[None])
    out = {"rot_deg": float(rot.mean()), "trans": float(tr.mean()), "rot_deg_max": float(rot.max()),
           "trans_max": float(tr.max()), "rot_deg_aligned": float(rot_a.mean()), "trans_aligned": float(tr_a.mean()),
           "gauge_rot_deg": float(gauge_r[0]), "gauge_trans": float(W[:3, 3].norm())}
    if rpe_r.numel():
        out.update(rpe_rot_deg=float(rpe_r.mean()), rpe_trans=float(rpe_t.mean()))
    return out

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

Also here: random pose perturbations of a given size and rotation/translation pose errors, used to
build and score refinement benchmarks.
"""
from __future__ import annotations

import math

import torch
from kornia.geometry.liegroup import Se3, So3


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


def perturb_viewmats(viewmats: torch.Tensor, rot_deg: float, trans: float,
                     generator: torch.Generator | None = None) -> torch.Tensor:
    """Perturb cameras ``[B,4,4]`` by random rotations of exactly ``rot_deg`` degrees (random axes,
    about the camera centre) and random camera-centre offsets of exactly length ``trans``.

    Returns the perturbed world→camera matrices ``[B,4,4]`` (same dtype/device).
    """
    B = viewmats.shape[0]
    dt = torch.float64
    axis = torch.nn.functional.normalize(torch.randn(B, 3, generator=generator, dtype=dt), dim=-1)
    dirs = torch.nn.functional.normalize(torch.randn(B, 3, generator=generator, dtype=dt), dim=-1)
    dR = So3.exp(axis * math.radians(rot_deg)).matrix()
    V = viewmats.detach().to(dt).cpu()
    R, t = V[:, :3, :3], V[:, :3, 3]
    centre = -(R.transpose(1, 2) @ t[..., None])[..., 0] + trans * dirs
    R2 = dR @ R
    out = torch.eye(4, dtype=dt).repeat(B, 1, 1)
    out[:, :3, :3] = R2
    out[:, :3, 3] = -(R2 @ centre[..., None])[..., 0]
    return out.to(viewmats)


def camera_centres(viewmats: torch.Tensor) -> torch.Tensor:
    """World positions ``[B, 3]`` of the optical centres of world→camera matrices ``[B,4,4]``."""
    R, t = viewmats[:, :3, :3], viewmats[:, :3, 3]
    return -(R.transpose(1, 2) @ t[..., None])[..., 0]


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

"""Camera paths for videos: an orbit around the training cameras' target, a smooth path through the training
cameras, and nerfstudio's ``camera_path.json``.

Every path is a :class:`CameraPath` of OpenCV world→camera ``viewmats`` with pinhole intrinsics at one image
size (docs/method.md conventions).

* :func:`orbit`: a circle at the training cameras' mean distance and height about the point nearest to all
  their optical axes, up = their mean up.
* :func:`smooth_path`: a nearest-neighbour tour through the training cameras (from the first), interpolated
  in arc length: camera centres by a cubic spline (:class:`scipy.interpolate.CubicSpline`), orientations by
  a rotation spline (:class:`scipy.spatial.transform.RotationSpline`, continuous angular velocity); the
  path passes through every training pose.
* :func:`read_nerfstudio_path`: nerfstudio's ``camera_path.json`` (what its viewer's "render" panel and
  ``ns-render camera-path`` use): ``render_width``, ``render_height``, ``fps`` and per frame
  ``camera_to_world`` (4×4, row-major, flattened or nested; OpenGL camera axes) and ``fov`` (vertical,
  degrees); ``camera_type`` must be ``perspective``.
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import torch
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from nsplat.cameras import camera_centres, look_at, opengl_c2w_to_viewmat, scale_intrinsics
from nsplat.errors import DataError


@dataclasses.dataclass
class CameraPath:
    """``F`` cameras of one image size.

    Attributes:
        viewmats: ``[F,4,4]`` float32 OpenCV world→camera. Ks: ``[F,3,3]`` float32 intrinsics in pixels.
        width, height: image size in pixels. fps: the frame rate the path asks for (``None``: the caller's).
    """

    viewmats: torch.Tensor
    Ks: torch.Tensor
    width: int
    height: int
    fps: float | None = None

    def __len__(self) -> int:
        return int(self.viewmats.shape[0])

    def resized(self, longest: int) -> "CameraPath":
        """The same cameras rendering ``longest`` pixels along the longer image side (intrinsics scaled)."""
        s = longest / max(self.width, self.height)
        width, height = max(1, round(self.width * s)), max(1, round(self.height * s))
        Ks = scale_intrinsics(self.Ks, width / self.width, height / self.height)
        return dataclasses.replace(self, Ks=Ks, width=width, height=height)


def orbit(viewmats: torch.Tensor, frames: int) -> torch.Tensor:
    """``[frames,4,4]`` cameras on a circle at the training cameras' (``viewmats [V,4,4]``) mean distance and
    elevation, looking at the point nearest to all their optical axes, up = mean camera up."""
    V = viewmats.double().cpu()
    R, t = V[:, :3, :3], V[:, :3, 3]
    eyes = -(R.transpose(1, 2) @ t[..., None])[..., 0]
    axes = R[:, 2, :]  # camera z (forward) in world coordinates
    up = -R[:, 1, :].mean(0)
    up = up / up.norm()
    # Least-squares point closest to all optical axes.
    P = torch.eye(3, dtype=torch.float64) - axes[:, :, None] * axes[:, None, :]
    target = torch.linalg.lstsq(P.sum(0), (P @ eyes[..., None]).sum(0)).solution[:, 0]
    rel = eyes - target
    height = float((rel @ up).mean())
    radius = float((rel - (rel @ up)[:, None] * up).norm(dim=-1).mean())
    e1 = torch.linalg.cross(up, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    if e1.norm() < 1e-6:
        e1 = torch.linalg.cross(up, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(up, e1)
    ang = torch.arange(frames, dtype=torch.float64) / frames * 2 * math.pi
    eye = target + radius * (torch.cos(ang)[:, None] * e1 + torch.sin(ang)[:, None] * e2) + height * up
    return look_at(eye, target.expand_as(eye), up).float()


def tour(centres: np.ndarray) -> list[int]:
    """A nearest-neighbour tour of the points ``centres [V,3]`` from the first: each next index is the nearest
    point not yet visited."""
    left = list(range(1, len(centres)))
    order = [0]
    while left:
        d = np.linalg.norm(centres[left] - centres[order[-1]], axis=1)
        order.append(left.pop(int(d.argmin())))
    return order


def smooth_path(viewmats: torch.Tensor, frames: int) -> tuple[torch.Tensor, np.ndarray]:
    """``([frames,4,4] viewmats, knots)``: the smooth path through the cameras ``viewmats [V,4,4]`` (module
    docstring), sampled at ``frames`` equal steps of arc length from the first to the last camera of the
    tour; ``knots [V']`` are the path parameters of the distinct training poses it passes through, in tour
    order (a camera repeating the previous one's centre is skipped)."""
    V = viewmats.double().cpu()
    order = tour(camera_centres(V).numpy())
    centres = camera_centres(V[order]).numpy()
    rot = V[order][:, :3, :3].transpose(1, 2).numpy()                      # camera→world rotations
    step = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    keep = np.concatenate([[True], step > 1e-9 * max(1.0, float(step.max(initial=0.0)))])
    centres, rot = centres[keep], rot[keep]
    if len(centres) == 1:
        return V[order[:1]].expand(frames, 4, 4).float().clone(), np.zeros(1)
    knots = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centres, axis=0), axis=1))])
    position = CubicSpline(knots, centres, axis=0)
    rotation = RotationSpline(knots, Rotation.from_matrix(rot))
    s = np.linspace(0.0, knots[-1], frames)
    c2w_R, c2w_t = rotation(s).as_matrix(), position(s)
    out = torch.zeros(frames, 4, 4, dtype=torch.float64)
    out[:, :3, :3] = torch.from_numpy(c2w_R).transpose(1, 2)
    out[:, :3, 3] = -(out[:, :3, :3] @ torch.from_numpy(c2w_t)[..., None])[..., 0]
    out[:, 3, 3] = 1.0
    return out.float(), knots


def read_nerfstudio_path(path: str | Path) -> CameraPath:
    """nerfstudio's ``camera_path.json`` (module docstring) as a :class:`CameraPath` in the file's world.

    Bad files raise a one-line :class:`~nsplat.errors.DataError` naming the file (and the frame and field)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--path: no camera path file at {path}")
    try:
        meta = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: not valid JSON: {exc}") from exc
    if not isinstance(meta, dict) or not isinstance(meta.get("camera_path"), list) or not meta["camera_path"]:
        raise DataError(f"{path}: expected an object with a non-empty list 'camera_path'")
    kind = meta.get("camera_type", "perspective")
    if kind != "perspective":
        raise DataError(f"{path}: camera_type {kind!r} is not supported (only 'perspective')")

    def number(where: str, key: str, value: object, positive: bool = True) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                or (positive and value <= 0):
            raise DataError(f"{path}: {where}field {key!r}: expected a {'positive ' if positive else ''}finite number, "
                            f"got {value!r}")
        return float(value)

    width = number("", "render_width", meta.get("render_width"))
    height = number("", "render_height", meta.get("render_height"))
    if width != int(width) or height != int(height):
        raise DataError(f"{path}: render_width/render_height must be whole numbers, got {width:g}, {height:g}")
    fps = number("", "fps", meta["fps"]) if "fps" in meta else None
    c2ws, fovs = [], []
    for i, frame in enumerate(meta["camera_path"]):
        where = f"frame {i}: "
        if not isinstance(frame, dict):
            raise DataError(f"{path}: {where}expected an object with camera_to_world and fov")
        try:
            m = np.array(frame.get("camera_to_world"), dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise DataError(f"{path}: {where}field 'camera_to_world': expected 16 numbers") from None
        if m.size not in (12, 16) or not np.isfinite(m).all():
            raise DataError(f"{path}: {where}field 'camera_to_world': expected 12 or 16 finite numbers, got {m.size}")
        c2w = np.eye(4)
        c2w[:3] = m.reshape(-1, 4)[:3]
        dev = float(np.abs(c2w[:3, :3].T @ c2w[:3, :3] - np.eye(3)).max())
        if dev > 1e-3 or np.linalg.det(c2w[:3, :3]) < 0:
            raise DataError(f"{path}: {where}field 'camera_to_world': the rotation part is not a rotation "
                            f"(|RᵀR - I| = {dev:.3g})")
        fov = number(where, "fov", frame.get("fov"))
        if fov >= 180:
            raise DataError(f"{path}: {where}field 'fov': expected a vertical field of view below 180 degrees, "
                            f"got {fov:g}")
        c2ws.append(c2w)
        fovs.append(fov)
    viewmats = opengl_c2w_to_viewmat(torch.from_numpy(np.stack(c2ws))).float()
    focal = torch.tensor([0.5 * height / math.tan(math.radians(f) / 2) for f in fovs], dtype=torch.float64)
    Ks = torch.zeros(len(fovs), 3, 3, dtype=torch.float64)
    Ks[:, 0, 0], Ks[:, 1, 1] = focal, focal
    Ks[:, 0, 2], Ks[:, 1, 2], Ks[:, 2, 2] = width / 2, height / 2, 1.0
    return CameraPath(viewmats, Ks.float(), int(width), int(height), fps)

"""3D Gaussian splatting's ``point_cloud.ply``: surfels written as flat Gaussians, and any such file read back.

Layout (binary little endian, one ``vertex`` element, one row per point, the original 3DGS order)::

    x y z                       float  position
    nx ny nz                    float  the surfel's unit normal (3DGS itself writes zeros here)
    f_dc_0 f_dc_1 f_dc_2        float  SH coefficient of band 0 per colour channel
    f_rest_0 … f_rest_44        float  bands 1-3: the 15 coefficients of red, then those of green, then blue
    opacity                     float  logit of the opacity
    scale_0 scale_1 scale_2     float  log standard deviations along the rotation's three axes
    rot_0 rot_1 rot_2 rot_3     float  unit quaternion (w, x, y, z) of that rotation

What this module writes (:func:`write_gaussian_ply`), exactly convertible both ways:

* **rotation and scales**: the rotation's axes are the op's tangent frame ``t0, t1`` of the normal
  (:func:`nsplat.ops.projection.tangent_frame`) and the normal ``n`` (``t0 × t1 = n``, so a proper rotation);
  ``scale_0, scale_1`` are the surfel's tangent std-devs ``s0, s1`` and ``scale_2``, the flat normal axis, is
  :data:`FLAT` times the larger of them;
* **colour**: 3DGS evaluates ``max(0, ½ + Σ_j Y'_j(d) c'_j)`` with its real SH basis ``Y'``, which is this
  project's basis (:mod:`nsplat.render.sh`) times ``(−1)^m`` for order ``m``; the project evaluates
  ``max(0, f_0 + Σ_{j≥1} Y_j(d) f_j)`` with the constant band folded into ``f_0``
  (:func:`nsplat.render.sh.view_colour`),
  so ``c'_0 = (f_0 − ½)/Y_0`` and ``c'_j = (−1)^m f_j``; a plain RGB colour is ``f_0`` with the higher
  bands zero. Every file has degree 3 (the layout 3DGS viewers expect); missing bands are zeros;
* **opacity**: the logit of the opacity (clamped to ``[1e-6, 1 − 1e-6]``).

**Render mode** (header comments, the conventions of gsplat/Brush and of a proposal on 3DGS's repository): an
antialiased file, meant for a rasteriser with Mip-Splatting's opacity compensation ``sqrt(det Σ'₀ / det Σ')``
(gsplat's ``antialiased``, PlayCanvas's ``GSPLAT_AA``), carries ``comment SplatRenderMode: mip`` and ``comment
train_flags antialiasing``; a classic one ``comment SplatRenderMode: default``. Reading
(:func:`file_render_mode`) honours the last ``SplatRenderMode`` comment (case-insensitive), else ``train_flags``
naming ``antialiasing``, else Postshot's ``antialiased 1``; a file without any is classic.

The values given are written as they are: ``export --format 3dgs`` first converts nsplat's opacities and
std-devs to 3DGS's kernel, and ``geometry.init: ply`` converts what this module reads back
(:mod:`nsplat.gaussians.kernel`).

Reading (:func:`read_gaussian_ply`, any 3DGS file): the quaternion is normalised, the normal is the axis of
the smallest scale, and ``s0, s1`` are the std-devs of the Gaussian's in-plane covariance along the op's
tangent axes of that normal. That is exact for the files written here and for Gaussians isotropic in their
plane; a Gaussian stretched along another in-plane direction becomes the axis-aligned surfel of the same
variances along ``t0, t1``, and every Gaussian's thickness is dropped (a surfel is flat).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement
from scipy.spatial.transform import Rotation

from nsplat.data.pointclouds import read_vertex_element
from nsplat.errors import DataError
from nsplat.ops.projection import tangent_frame
from nsplat.render.sh import MAX_VIEW_DEGREE, view_channels

#: 3DGS's ``C0``: the constant SH basis function ``1/(2√π)``.
SH_C0 = 0.5 / math.sqrt(math.pi)
#: The flat axis' std-dev relative to the surfel's larger tangent std-dev.
FLAT = 1e-3
#: Opacities are clamped to ``[OPACITY_EPS, 1 − OPACITY_EPS]`` before the logit.
OPACITY_EPS = 1e-6
#: Header comments of each render mode.
MODE_COMMENTS = {"classic": ["SplatRenderMode: default"],
                 "antialiased": ["SplatRenderMode: mip", "train_flags antialiasing"]}
#: Properties that mark a 3DGS file (besides ``f_rest_*``).
REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3")


def _orders(degree: int) -> np.ndarray:
    """Order ``m`` of each SH basis function ``j = 1 … (degree+1)² − 1`` (bands 1..degree, ``m = −l … l``)."""
    return np.array([m for band in range(1, degree + 1) for m in range(-band, band + 1)], dtype=np.int64)


def to_gaussian_sh(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(f_dc [N,3], f_rest [N,45])`` of this project's view-dependent colour ``features [N, 3·(L+1)²]``
    (channels ``3j..3j+2``: basis function ``j``'s RGB coefficient; ``L ≤ 3``; see the module docstring)."""
    K = features.shape[1] // 3
    degree = math.isqrt(K) - 1
    if features.shape[1] != view_channels(degree):
        raise ValueError(f"features: expected 3·(L+1)² channels (3, 12, 27 or 48), got {features.shape[1]}")
    coeff = features.reshape(-1, K, 3).astype(np.float64)               # [N, K, RGB]
    f_dc = (coeff[:, 0] - 0.5) / SH_C0
    rest = np.zeros((features.shape[0], view_channels(MAX_VIEW_DEGREE) // 3 - 1, 3))
    rest[:, :K - 1] = coeff[:, 1:] * np.where(_orders(degree) % 2, -1.0, 1.0)[None, :, None]
    return f_dc, rest.transpose(0, 2, 1).reshape(features.shape[0], -1)  # channel-major: all of R, then G, B


def from_gaussian_sh(f_dc: np.ndarray, f_rest: np.ndarray, degree: int) -> np.ndarray:
    """This project's colour features ``[N, 3·(degree+1)²]`` from 3DGS's ``f_dc [N,3]`` and ``f_rest
    [N, 3·((L+1)² − 1)]`` (the file's degree ``L``; bands above ``degree`` are dropped, missing ones zero)."""
    N = f_dc.shape[0]
    K_file = f_rest.shape[1] // 3 + 1
    K = (degree + 1) ** 2
    coeff = np.zeros((N, K, 3))
    coeff[:, 0] = 0.5 + SH_C0 * f_dc
    rest = f_rest.reshape(N, 3, K_file - 1).transpose(0, 2, 1)          # [N, K_file − 1, RGB]
    n = min(K, K_file) - 1
    signs = np.where(_orders(MAX_VIEW_DEGREE)[:n] % 2, -1.0, 1.0)
    coeff[:, 1:n + 1] = rest[:, :n] * signs[None, :, None]
    return coeff.reshape(N, 3 * K)


def surfel_rotations(normals: np.ndarray) -> np.ndarray:
    """``[N,4]`` quaternions ``(w, x, y, z)`` of the rotations whose columns are ``t0, t1, n`` for unit normals
    ``normals [N,3]`` (the op's tangent frame)."""
    n = torch.from_numpy(normals.astype(np.float64))
    t0, t1 = tangent_frame(n)
    R = torch.stack([t0, t1, n], dim=-1).numpy()                        # columns t0, t1, n
    return Rotation.from_matrix(R).as_quat(scalar_first=True)


def write_gaussian_ply(path: str | Path, means: np.ndarray, normals: np.ndarray, scales: np.ndarray,
                       opacities: np.ndarray, features: np.ndarray, *, antialiased: bool = False) -> Path:
    """Write surfels as 3DGS Gaussians (module docstring); returns the path.

    Args:
        means ``[N,3]``, normals ``[N,3]`` (unit), scales ``[N,2]`` tangent std-devs, opacities ``[N]`` in
        [0, 1], features ``[N, 3·(L+1)²]``: RGB colour (``L = 0``) or view-dependent SH colour.
        antialiased: mark the file for Mip-Splatting's compensation (header comments; the values are as given).
    """
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    f_dc, f_rest = to_gaussian_sh(features)
    o = np.clip(opacities.astype(np.float64), OPACITY_EPS, 1.0 - OPACITY_EPS)
    s = scales.astype(np.float64)
    log_s = np.log(np.concatenate([s, FLAT * s.max(1, keepdims=True)], 1))
    cols = [*(means[:, i] for i in range(3)), *(n[:, i] for i in range(3)), *(f_dc[:, i] for i in range(3)),
            *(f_rest[:, i] for i in range(f_rest.shape[1])), np.log(o) - np.log1p(-o),
            *(log_s[:, i] for i in range(3)), *surfel_rotations(n).T]
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(f_rest.shape[1])] + ["opacity", "scale_0", "scale_1", "scale_2"]
             + [f"rot_{i}" for i in range(4)])
    arr = np.empty(means.shape[0], dtype=[(name, "<f4") for name in names])
    for name, col in zip(names, cols):
        arr[name] = col
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    comments = MODE_COMMENTS["antialiased" if antialiased else "classic"]
    PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<", comments=comments).write(str(path))
    return path


def file_render_mode(comments: list[str]) -> str:
    """``"antialiased"`` or ``"classic"``: the render mode a PLY header's ``comments`` (without the word
    ``comment``) declare (module docstring)."""
    mode = None
    for c in comments:
        words = c.lower().replace(":", " ").split()
        if words[:1] == ["splatrendermode"] and len(words) > 1:
            mode = "antialiased" if words[1] == "mip" else "classic"
    if mode is not None:
        return mode
    flags = any(w[:1] == ["train_flags"] and "antialiasing" in w[1:] for w in (c.lower().split() for c in comments))
    postshot = any(c.lower().split() == ["antialiased", "1"] for c in comments)
    return "antialiased" if flags or postshot else "classic"


def is_gaussian_ply(names: set[str]) -> bool:
    """Whether a ``vertex`` element with properties ``names`` is in 3DGS's layout."""
    return all(k in names for k in REQUIRED)


def read_gaussian_ply(path: str | Path) -> dict[str, torch.Tensor | int | bool]:
    """Read a 3DGS PLY (any tool's) as surfels (module docstring).

    Returns:
        ``means [N,3]``, ``normals [N,3]`` (unit), ``scales [N,2]``, ``opacities [N]`` (float64 tensors),
        ``features [N, 3·(L+1)²]`` (this project's colour convention), ``degree`` ``L`` (from the number of
        ``f_rest_*`` properties) and ``antialiased`` (the header's render mode, :func:`file_render_mode`). Bad
        files raise a one-line :class:`~nsplat.errors.DataError` naming them.
    """
    path, v, names = read_vertex_element(path)
    antialiased = file_render_mode(PlyData.read(str(path), mmap=True).comments) == "antialiased"
    missing = [k for k in REQUIRED if k not in names]
    if missing:
        raise DataError(f"{path}: not a 3D Gaussian splatting PLY: missing properties {missing}")
    rest_count = sum(1 for k in names if k.startswith("f_rest_"))
    degree = math.isqrt(rest_count // 3 + 1) - 1
    if rest_count % 3 or (degree + 1) ** 2 != rest_count // 3 + 1 or degree > MAX_VIEW_DEGREE:
        raise DataError(f"{path}: {rest_count} f_rest properties: expected 3·((L+1)² − 1) for a degree L ≤ "
                        f"{MAX_VIEW_DEGREE} (0, 9, 24 or 45)")
    if v.count == 0:
        raise DataError(f"{path}: the PLY has zero vertices")

    def cols(keys: list[str]) -> np.ndarray:
        try:
            return np.stack([np.asarray(v[k], np.float64) for k in keys], 1)
        except (TypeError, ValueError) as exc:
            raise DataError(f"{path}: properties {keys[0]}… must be numeric scalars: {exc}") from None

    means, f_dc, opac = cols(["x", "y", "z"]), cols(["f_dc_0", "f_dc_1", "f_dc_2"]), cols(["opacity"])[:, 0]
    f_rest = cols([f"f_rest_{i}" for i in range(rest_count)]) if rest_count else np.zeros((v.count, 0))
    log_s, quat = cols(["scale_0", "scale_1", "scale_2"]), cols(["rot_0", "rot_1", "rot_2", "rot_3"])
    bad = ~np.isfinite(np.concatenate([means, f_dc, f_rest, opac[:, None], log_s, quat], 1)).all(1)
    bad |= np.linalg.norm(quat, axis=1) == 0
    if bad.any():
        raise DataError(f"{path}: {int(bad.sum())} Gaussians have NaN, Inf or a zero quaternion, first at vertex "
                        f"{int(np.nonzero(bad)[0][0])}")
    R = Rotation.from_quat(quat, scalar_first=True).as_matrix()          # [N,3,3], columns = axes
    s = np.exp(log_s)
    flat = s.argmin(1)
    normals = np.take_along_axis(R, flat[:, None, None].repeat(3, 1), 2)[..., 0]
    t0, t1 = (t.numpy() for t in tangent_frame(torch.from_numpy(normals)))
    cov = np.einsum("nij,nj,nkj->nik", R, s**2 * (np.arange(3)[None] != flat[:, None]), R)  # in-plane part
    scales = np.sqrt(np.stack([np.einsum("ni,nij,nj->n", t, cov, t) for t in (t0, t1)], 1))
    return {"means": torch.from_numpy(means), "normals": torch.from_numpy(normals),
            "scales": torch.from_numpy(scales), "opacities": torch.from_numpy(1.0 / (1.0 + np.exp(-opac))),
            "features": torch.from_numpy(from_gaussian_sh(f_dc, f_rest, degree)), "degree": degree,
            "antialiased": antialiased}

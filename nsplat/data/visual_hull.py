"""Initial surfels from posed silhouettes: voxel visual hull → surface voxels with normals and colours.

A voxel grid over a bounding box is carved by every view's (slightly dilated) alpha mask: a voxel
survives when it projects onto coverage ``>= alpha_threshold`` in every view that sees it (in front
of the camera and inside the image) and enough views see it. The surviving voxels that touch a carved neighbour are
the surface; their
normals are the negated gradient of the Gaussian-smoothed occupancy, and their colour is the median
of the image colours over the views the normal faces. This is a starting point for fitting with the
op (stage 1 of the neural task), not a reconstruction in itself: concavities stay filled.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch
from scipy import ndimage

from nsplat.cameras import camera_centres, look_at_point
from nsplat.data.views import PosedViews


@dataclasses.dataclass
class HullPoints:
    """Surface samples of a visual hull.

    Attributes:
        means: ``[N, 3]`` voxel centres on the hull surface (world units).
        normals: ``[N, 3]`` unit outward normals.
        colours: ``[N, 3]`` median observed RGB in [0, 1].
        voxel: edge length of a voxel (world units).
    """

    means: torch.Tensor
    normals: torch.Tensor
    colours: torch.Tensor
    voxel: float


def _project(points: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates ``[P,2]`` and camera depth ``[P]`` of world ``points [P,3]``."""
    q = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = q[:, 2]
    uv = (q[:, :2] / z.clamp_min(1e-9)[:, None]) @ K[:2, :2].T + K[:2, 2]
    return uv, z


def _lookup(img: torch.Tensor, uv: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest-pixel values of ``img [H,W,C]`` at ``uv [P,2]``; also the in-view mask ``[P]``."""
    H, W = img.shape[:2]
    col, row = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
    inside = (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
    vals = img[row.clamp(0, H - 1), col.clamp(0, W - 1)]
    return vals, inside


def carve(views: PosedViews, bbox: tuple[float, ...], grid: int, alpha_threshold: float = 0.5, dilate: int = 1,
          min_seen: float = 0.5) -> np.ndarray:
    """Occupancy ``[grid, grid, grid]`` (bool, index order x, y, z) of the visual hull in ``bbox``.

    Args:
        views: posed images with coverage ``masks [B,H,W]``.
        bbox: ``(xmin, ymin, zmin, xmax, ymax, zmax)`` world bounds of the grid.
        grid: voxels per side.
        alpha_threshold: coverage at or above which a pixel counts as inside the silhouette.
        dilate: silhouettes are grown by this many pixels first (keeps structures thinner than a
            voxel, e.g. a flat panel seen edge-on).
        min_seen: a voxel must project into at least this fraction of the views (voxels that
            almost no camera sees cannot be carved and are dropped instead).
    """
    centres = voxel_centres(bbox, grid)
    occ = torch.ones(centres.shape[0], dtype=torch.bool)
    seen = torch.zeros(centres.shape[0])
    for v in range(len(views)):
        mask = (views.masks[v] >= alpha_threshold).float()
        if dilate > 0:
            k = 2 * dilate + 1
            mask = torch.nn.functional.max_pool2d(mask[None, None], k, stride=1, padding=dilate)[0, 0]
        uv, z = _project(centres, views.viewmats[v].double(), views.Ks[v].double())
        inside_sil, inside = _lookup(mask[..., None], uv, z)
        occ &= ~inside | (inside_sil[:, 0] > 0)
        seen += inside.float()
    occ &= seen >= min_seen * len(views)
    return occ.reshape(grid, grid, grid).numpy()


def silhouette_box(views: PosedViews, *, grid: int = 48, margin: float = 0.05, passes: int = 2,
                   alpha_threshold: float = 0.5, dilate: int = 1, min_seen: float = 0.5) -> tuple[float, ...]:
    """The scene's box from its cameras and silhouettes: ``(xmin, ymin, zmin, xmax, ymax, zmax)`` around the
    volume that every view's mask covers (the visual hull), grown by one voxel and ``margin`` of its size a side.

    The search starts from the cube around the point nearest to all optical axes whose half-side is the largest
    camera distance from it (the cameras look at the object from outside it), carves it at ``grid`` voxels a
    side with :func:`carve`, and carves again inside the box found (``passes`` times in all), so the box tightens
    to about one voxel of the last grid whatever the scene's scale and place.

    Args:
        views: posed training images with coverage ``masks [B,H,W]``.
        grid: voxels per side of each pass. margin: growth of the final box, a fraction of its size per side.
        passes: carving passes (the first in the cameras' cube). alpha_threshold, dilate, min_seen: as in
            :func:`carve`.

    Raises:
        ValueError: the hull is empty (no voxel lies inside every silhouette).
    """
    centre, _ = look_at_point(views.viewmats)
    half = float((camera_centres(views.viewmats.double()) - centre).norm(dim=1).max())
    lo, hi = centre - half, centre + half
    for _ in range(passes):
        box = tuple(lo.tolist() + hi.tolist())
        occ = carve(views, box, grid, alpha_threshold, dilate, min_seen)
        if not occ.any():
            raise ValueError(f"the scene's box: no voxel of {[round(v, 3) for v in box]} lies inside every "
                             "silhouette (check the masks and the cameras, or set geometry.bbox)")
        idx = torch.from_numpy(np.argwhere(occ))
        voxel = (hi - lo) / grid
        new_lo = lo + (idx.min(0).values - 1) * voxel
        new_hi = lo + (idx.max(0).values + 2) * voxel
        lo, hi = torch.maximum(new_lo, lo), torch.minimum(new_hi, hi)
    grow = margin * (hi - lo)
    return tuple((lo - grow).tolist() + (hi + grow).tolist())


def voxel_centres(bbox: tuple[float, ...], grid: int) -> torch.Tensor:
    """``[grid³, 3]`` float64 centres of the grid's voxels, x slowest, z fastest."""
    if len(bbox) != 6 or not all(bbox[i] < bbox[i + 3] for i in range(3)):
        raise ValueError(f"bbox: expected (xmin, ymin, zmin, xmax, ymax, zmax) with min < max, got {bbox}")
    if grid < 2:
        raise ValueError(f"grid: expected >= 2 voxels per side, got {grid}")
    axes = [torch.linspace(bbox[i], bbox[i + 3], grid + 1, dtype=torch.float64) for i in range(3)]
    mids = [0.5 * (a[1:] + a[:-1]) for a in axes]
    return torch.stack(torch.meshgrid(*mids, indexing="ij"), -1).reshape(-1, 3)


def hull_points(views: PosedViews, bbox: tuple[float, ...], grid: int, *, alpha_threshold: float = 0.5,
                dilate: int = 1, min_seen: float = 0.5, max_points: int | None = None,
                seed: int = 0) -> HullPoints:
    """Surface voxels of the visual hull of ``views`` with normals and colours.

    Args:
        views: posed training images (``images`` composited on any background, ``masks``).
        bbox, grid, alpha_threshold, dilate, min_seen: as in :func:`carve`.
        max_points: keep a uniformly random subset of at most this many (``None``: all).
        seed: seed of that subset.

    Returns:
        :class:`HullPoints` (float32). Raises ``ValueError`` when the hull is empty.
    """
    occ = carve(views, bbox, grid, alpha_threshold, dilate, min_seen)
    if not occ.any():
        raise ValueError("visual hull is empty: check the bounding box and the cameras (no voxel lies inside "
                         "every silhouette)")
    outside_nb = ndimage.binary_dilation(~occ, structure=ndimage.generate_binary_structure(3, 1),
                                         border_value=1)
    surface = occ & outside_nb
    smooth = ndimage.gaussian_filter(occ.astype(np.float64), sigma=1.0, mode="constant")
    voxel = np.array([(bbox[i + 3] - bbox[i]) / grid for i in range(3)])
    grad = np.stack(np.gradient(smooth, *voxel), -1)
    idx = np.argwhere(surface)
    if max_points is not None and idx.shape[0] > max_points:
        rng = np.random.default_rng(seed)
        idx = idx[np.sort(rng.choice(idx.shape[0], max_points, replace=False))]
    means = torch.from_numpy(np.asarray(bbox[:3]) + (idx + 0.5) * voxel)
    g = -grad[idx[:, 0], idx[:, 1], idx[:, 2]]
    norm = np.linalg.norm(g, axis=-1, keepdims=True)
    fallback = means.numpy() - means.numpy().mean(0)  # flat gradient (isolated voxel): point outwards
    g = np.where(norm > 1e-12, g / np.maximum(norm, 1e-12), fallback)
    normals = torch.nn.functional.normalize(torch.from_numpy(g), dim=-1)
    colours = _median_colours(views, means, normals)
    return HullPoints(means=means.float(), normals=normals.float(), colours=colours.float(),
                      voxel=float(voxel.mean()))


def _median_colours(views: PosedViews, means: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """Median observed colour ``[N,3]`` over the views each point's normal faces (grey if none)."""
    samples = torch.full((len(views), means.shape[0], 3), float("nan"), dtype=torch.float64)
    for v in range(len(views)):
        V = views.viewmats[v].double()
        uv, z = _project(means, V, views.Ks[v].double())
        rgb, inside = _lookup(views.images[v].double(), uv, z)
        eye = -(V[:3, :3].T @ V[:3, 3])
        facing = ((eye - means) * normals).sum(-1) > 0
        ok = inside & facing
        samples[v, ok] = rgb[ok]
    med = torch.nanmedian(samples, dim=0).values
    return torch.where(torch.isnan(med), torch.full_like(med, 0.5), med)

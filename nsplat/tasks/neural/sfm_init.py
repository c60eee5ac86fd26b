"""Initial surfels from a structure-from-motion point cloud (COLMAP's ``points3D``), for photos without masks.

:func:`sfm_surfels` turns :class:`~nsplat.data.capture.SfmPoints` into surfels in four steps:

1. **outliers by the SfM's own evidence**: points seen in fewer than ``min_track`` images or with a mean
   reprojection error above ``max_error`` pixels are dropped (COLMAP keeps two-view points and points up
   to its 4-pixel filter threshold; both are the least reliable);
2. **outliers by isolation**: of the rest, points whose mean distance to their ``k`` nearest neighbours
   exceeds the mean of that distance by ``std_ratio`` standard deviations are dropped (the statistical
   outlier filter of PCL and Open3D);
3. **normals** from a plane fit to each point's ``k`` nearest neighbours (the eigenvector of the smallest
   eigenvalue of their covariance), oriented towards the centroid of the camera centres (the op has no
   back-face culling, so the sign only makes the output tidy);
4. **scales**: the mean distance to the 3 nearest neighbours (the spacing the hull initialisation uses),
   capped at ``max_spacing_quantile`` of all spacings so that a few sparse points do not become
   surfels that cover the whole image.

Neighbour queries use scipy's k-d tree.

:func:`fill_points` adds random points where the SfM found few (3DGS's random start when points are
missing, with a mask-free carve): uniform in a box, kept only where at least a fraction of the training
cameras see them, coloured with the mean of the training pixels they project to.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

from nsplat.data.capture import SfmPoints
from nsplat.data.views import PosedViews
from nsplat.tasks.neural.background import project


@dataclasses.dataclass
class SfmSurfels:
    """Surfels made from ``N`` SfM points.

    Attributes:
        means: ``[N,3]`` float32 positions. normals: ``[N,3]`` float32 unit normals.
        colours: ``[N,3]`` float32 RGB in [0, 1]. spacing: ``[N]`` float32 neighbour spacing (world units).
        index: ``[N]`` int64 rows of the kept points in the input :class:`SfmPoints`.
    """

    means: torch.Tensor
    normals: torch.Tensor
    colours: torch.Tensor
    spacing: torch.Tensor
    index: torch.Tensor


def reliable(points: SfmPoints, min_track: int = 3, max_error: float = 2.0) -> torch.Tensor:
    """``[P]`` bool: points seen in at least ``min_track`` images with a mean reprojection error of at most
    ``max_error`` pixels (an error of -1, i.e. unknown, passes)."""
    return (points.track_length >= min_track) & (points.error <= max_error)


def isolated(xyz: np.ndarray, k: int = 8, std_ratio: float = 2.0) -> np.ndarray:
    """``[P]`` bool: points of ``xyz [P,3]`` whose mean distance to their ``k`` nearest neighbours is more
    than ``std_ratio`` standard deviations above the mean of that distance."""
    k = min(k, len(xyz) - 1)
    dist, _ = cKDTree(xyz).query(xyz, k=k + 1)
    mean = dist[:, 1:].mean(1)
    return mean > mean.mean() + std_ratio * mean.std()


def plane_normals(xyz: np.ndarray, k: int = 8) -> np.ndarray:
    """``[P,3]`` unit normals of the least-squares planes through each point's ``k`` nearest neighbours
    (the point included) in ``xyz [P,3]``: the eigenvector of their covariance's smallest eigenvalue."""
    k = min(k, len(xyz) - 1)
    _, idx = cKDTree(xyz).query(xyz, k=k + 1)
    nb = xyz[idx]                                              # [P,k+1,3]
    centred = nb - nb.mean(1, keepdims=True)
    cov = np.einsum("pki,pkj->pij", centred, centred)
    _, vecs = np.linalg.eigh(cov)                              # ascending eigenvalues
    return vecs[:, :, 0]


def sfm_surfels(points: SfmPoints, camera_centres: torch.Tensor, *, min_track: int = 3, max_error: float = 2.0,
                k: int = 8, std_ratio: float = 2.0, max_spacing_quantile: float = 0.95) -> SfmSurfels:
    """Surfels from ``points`` (see the module docstring).

    Args:
        points: the SfM points (``P`` of them).
        camera_centres: ``[V,3]`` camera centres in the points' world (normal orientation).
        min_track, max_error: the SfM-evidence filter (:func:`reliable`).
        k, std_ratio: neighbours of the plane fit and of the isolation filter (:func:`isolated`).
        max_spacing_quantile: spacings are capped at this quantile of all spacings.

    Returns:
        :class:`SfmSurfels`. Raises ``ValueError`` naming the filter when fewer than 4 points remain.
    """
    if k < 3:
        raise ValueError(f"k: expected >= 3 neighbours for a plane fit, got {k}")
    if not 0.0 < max_spacing_quantile <= 1.0:
        raise ValueError(f"max_spacing_quantile: expected a fraction in (0, 1], got {max_spacing_quantile}")
    keep = reliable(points, min_track, max_error).numpy()
    if keep.sum() < 4:
        raise ValueError(f"SfM points: {int(keep.sum())} of {len(points)} have track length >= {min_track} and "
                         f"reprojection error <= {max_error} px; need at least 4 (lower min_track or raise max_error)")
    index = np.flatnonzero(keep)
    xyz = points.xyz.double().numpy()[index]
    lonely = isolated(xyz, k, std_ratio)
    index, xyz = index[~lonely], xyz[~lonely]
    if len(index) < 4:
        raise ValueError(f"SfM points: {len(index)} left after removing isolated points; need at least 4")
    normals = plane_normals(xyz, k)
    towards = camera_centres.double().numpy().mean(0) - xyz
    normals *= np.where((normals * towards).sum(1, keepdims=True) < 0, -1.0, 1.0)
    dist, _ = cKDTree(xyz).query(xyz, k=min(3, len(xyz) - 1) + 1)
    spacing = dist[:, 1:].mean(1)
    spacing = np.minimum(spacing, np.quantile(spacing, max_spacing_quantile))
    return SfmSurfels(means=torch.from_numpy(xyz).float(), normals=torch.from_numpy(normals).float(),
                      colours=points.rgb[torch.from_numpy(index)].float(), spacing=torch.from_numpy(spacing).float(),
                      index=torch.from_numpy(index).long())


def fill_box(xyz: torch.Tensor, margin: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(lo [3], hi [3])`` float64: the axis-aligned box of ``xyz [P,3]`` grown by ``margin`` times its size
    on each side."""
    lo, hi = xyz.double().min(0).values, xyz.double().max(0).values
    return lo - margin * (hi - lo), hi + margin * (hi - lo)


def fill_points(lo: torch.Tensor, hi: torch.Tensor, views: PosedViews, count: int, min_seen: float,
                generator: torch.Generator, rounds: int = 50) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``count`` random points uniform in the box ``lo [3]``..``hi [3]`` that at least ``min_seen`` of the
    ``V`` training ``views`` see (in front of the camera, inside the image): a carve of the box by the
    camera frusta, without masks.

    Args:
        lo, hi: box corners. views: the training views (``images [V,H,W,3]``). count: points wanted.
        min_seen: fraction (0, 1] of the views that must see a point. generator: draws (CPU).
        rounds: at most this many batches of ``4·count`` candidates are drawn.

    Returns:
        ``(means [count,3], normals [count,3], colours [count,3])`` float32: normals uniformly random,
        colours the mean of the bilinearly sampled pixels of the views that see the point. Raises
        ``ValueError`` when fewer than ``count`` candidates pass within ``rounds`` batches.
    """
    if count < 1:
        raise ValueError(f"count: expected >= 1 fill points, got {count}")
    if not 0.0 < min_seen <= 1.0:
        raise ValueError(f"min_seen: expected a fraction in (0, 1], got {min_seen}")
    lo, hi = lo.double().cpu(), hi.double().cpu()
    kept: list[torch.Tensor] = []
    total = 0
    for _ in range(rounds):
        cand = lo + (hi - lo) * torch.rand(4 * count, 3, generator=generator, dtype=torch.float64)
        _, _, inside = project(cand, views)                     # [V,4·count]
        cand = cand[inside.double().mean(0) >= min_seen - 1e-9]
        kept.append(cand)
        total += len(cand)
        if total >= count:
            break
    if total < count:
        raise ValueError(f"only {total} of {count} random points in the box {lo.tolist()}..{hi.tolist()} are seen "
                         f"by {min_seen:.0%} of the {len(views)} training views (lower the fraction or the count)")
    means = torch.cat(kept)[:count]
    uv, _, inside = project(means, views)
    grid = (uv / torch.tensor([views.width, views.height], dtype=torch.float64) * 2.0 - 1.0).float()
    samples = F.grid_sample(views.images.permute(0, 3, 1, 2).float(), grid[:, :, None, :], mode="bilinear",
                            padding_mode="border", align_corners=False)[:, :, :, 0]   # [V,3,count]
    w = inside.float()
    colours = (samples * w[:, None, :]).sum(0).T / w.sum(0).clamp_min(1.0)[:, None]
    normals = F.normalize(torch.randn(count, 3, generator=generator), dim=-1)
    return means.float(), normals, colours.clamp(0.0, 1.0)

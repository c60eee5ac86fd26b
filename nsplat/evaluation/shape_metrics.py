"""Point-cloud distances for shape reconstruction (paper Table 1–3), with a KD-tree.

Two definitions, both on coordinates divided by the ground-truth bounding-box diagonal ``D``:

* **authors'** (``*_sq``, what the DSS/paper evaluation code computes): squared nearest-neighbour
  distances ``d²``; Chamfer = ``max(mean_a d²(a→B), mean_b d²(b→A))``; Hausdorff =
  ``max(max_a d²(a→B), max_b d²(b→A))``. Because coordinates are divided by ``D`` first, these are
  squared distances in units of ``D²``.
* **plain** (``chamfer``, ``hausdorff``): Euclidean nearest-neighbour distances; Chamfer =
  ``½ (mean_a d(a→B) + mean_b d(b→A))`` (mean of the two directional means); Hausdorff =
  ``max(max_a d(a→B), max_b d(b→A))``. Units of ``D``.
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree


def _points(x: np.ndarray | torch.Tensor, name: str) -> np.ndarray:
    a = x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 1:
        raise ValueError(f"{name}: expected a point array of shape [N, 3] with N >= 1, got {list(a.shape)}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: contains NaN or Inf")
    return a


def nn_distances(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Euclidean distance from each point of ``src [N,3]`` to its nearest neighbour in ``dst [M,3]``: ``[N]``."""
    dist, _ = cKDTree(dst).query(src, k=1)
    return dist


def bbox_diagonal(points: np.ndarray | torch.Tensor) -> float:
    """Length of the axis-aligned bounding-box diagonal of ``points [N,3]``."""
    p = _points(points, "points")
    return float(np.linalg.norm(p.max(0) - p.min(0)))


def point_cloud_distances(pred: np.ndarray | torch.Tensor, gt: np.ndarray | torch.Tensor) -> dict[str, float]:
    """Chamfer and Hausdorff distances between ``pred [N,3]`` and ``gt [M,3]`` (see module docstring).

    Returns:
        ``{"chamfer_sq", "hausdorff_sq"}`` (authors' squared definition, units of ``D²``),
        ``{"chamfer", "hausdorff"}`` (plain distances, units of ``D``) and ``"diagonal"`` (``D``).
    """
    p, g = _points(pred, "pred"), _points(gt, "gt")
    diag = float(np.linalg.norm(g.max(0) - g.min(0)))
    if diag <= 0:
        raise ValueError("gt: bounding-box diagonal is zero (all points coincide)")
    d_pg = nn_distances(p, g) / diag
    d_gp = nn_distances(g, p) / diag
    return {
        "chamfer_sq": float(max(np.mean(d_pg ** 2), np.mean(d_gp ** 2))),
        "hausdorff_sq": float(max(np.max(d_pg ** 2), np.max(d_gp ** 2))),
        "chamfer": float(0.5 * (np.mean(d_pg) + np.mean(d_gp))),
        "hausdorff": float(max(np.max(d_pg), np.max(d_gp))),
        "diagonal": diag,
    }

"""Point clouds for shape reconstruction, via plyfile: the DSS shapes (bunny, teapot, yoga1, yoga6) or any PLY.

The DSS files live in ``<data root>/dss_pointclouds/`` (by default :func:`nsplat.data.paths.data_root`;
``nsplat data fetch dss`` downloads them there). Each is a PLY with a ``vertex`` element carrying ``x y z nx ny nz``.
Any other PLY with ``x y z`` loads through :func:`load_shape`; where it has no normals they are estimated
(:func:`estimate_normals`). Points are used in the file's own units: the cameras are placed relative to the
cloud's bounding-box centre and enclosing radius, and the reconstruction metrics are reported both raw and
divided by the ground truth's bounding-box diagonal (:mod:`nsplat.evaluation.shape_metrics`).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
from scipy.spatial import cKDTree

from nsplat.config import ConfigError
from nsplat.data.paths import data_root
from nsplat.errors import DataError

#: Shape name → file name inside ``dss_pointclouds/``.
DSS_SHAPES: dict[str, str] = {
    "bunny": "bunny-8000.ply",
    "teapot": "teapot_normal_dense.ply",
    "yoga1": "yoga1_out.ply",
    "yoga6": "yoga6_out.ply",
}


def default_data_root() -> Path:
    """The data folder (:func:`nsplat.data.paths.data_root`)."""
    return data_root()


@dataclasses.dataclass
class PointCloud:
    """An oriented point cloud.

    Attributes:
        points: ``[N,3]`` positions. normals: ``[N,3]`` unit normals. name: shape name or file stem.
    """

    points: torch.Tensor
    normals: torch.Tensor
    name: str

    @property
    def center(self) -> torch.Tensor:
        """``[3]`` centre of the axis-aligned bounding box."""
        return 0.5 * (self.points.min(0).values + self.points.max(0).values)

    @property
    def radius(self) -> float:
        """Largest distance of a point from :attr:`center` (radius of the enclosing sphere about it)."""
        return float((self.points - self.center).norm(dim=-1).max())


def check_ply_header(path: Path) -> None:
    """Reject PLY headers that make plyfile crash the process or misbehave, before it parses the file.

    An element without properties in a binary file makes numpy divide by a zero item size (SIGFPE), so
    every element must declare at least one property and a non-negative integer count.
    """
    with open(path, "rb") as fh:
        head = fh.read(65536)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise DataError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header' in the first 64 KiB)")
    element, props = None, 0
    for raw in head[:end].split(b"\n")[1:]:
        words = raw.decode("ascii", "replace").split()
        if not words:
            continue
        if words[0] == "element":
            if element is not None and props == 0:
                raise DataError(f"{path}: PLY element {element!r} declares no properties")
            if len(words) != 3 or not words[2].isdigit():
                raise DataError(f"{path}: malformed PLY element line {' '.join(words)!r} "
                                f"(expected 'element NAME COUNT')")
            element, props = words[1], 0
        elif words[0] == "property":
            props += 1
    if element is not None and props == 0:
        raise DataError(f"{path}: PLY element {element!r} declares no properties")


def read_oriented_ply(path: str | Path, dtype: torch.dtype = torch.float32) -> PointCloud:
    """Read ``x y z nx ny nz`` from the ``vertex`` element of a PLY; normals are normalised.

    Raises ``FileNotFoundError`` for a missing file and :class:`~nsplat.errors.DataError` (a ``ValueError``)
    naming the file for unreadable files, missing properties, zero vertices, NaN/Inf values or zero-length
    normals.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: no PLY file at {path}")
    check_ply_header(path)
    try:
        ply = PlyData.read(str(path))
    except Exception as exc:  # noqa: BLE001 - plyfile's parse errors do not name the file
        raise DataError(f"{path}: not a readable PLY file (truncated or corrupt?): {exc}") from exc
    if "vertex" not in [e.name for e in ply.elements]:
        raise DataError(f"{path}: no 'vertex' element")
    v = ply["vertex"]
    names = set(v.data.dtype.names)
    missing = [k for k in ("x", "y", "z", "nx", "ny", "nz") if k not in names]
    if missing:
        raise DataError(f"{path}: missing vertex properties {missing}")
    try:
        pts = np.stack([np.asarray(v[k], np.float64) for k in ("x", "y", "z")], 1)
        nrm = np.stack([np.asarray(v[k], np.float64) for k in ("nx", "ny", "nz")], 1)
    except (TypeError, ValueError) as exc:  # list properties, non-numeric data
        raise DataError(f"{path}: vertex properties x y z nx ny nz must be numeric scalars: {exc}") from None
    if pts.shape[0] == 0:
        raise DataError(f"{path}: the PLY has zero vertices")
    for what, arr in (("coordinates (x y z)", pts), ("normals (nx ny nz)", nrm)):
        bad = ~np.isfinite(arr).all(1)
        if bad.any():
            raise DataError(f"{path}: {int(bad.sum())} vertices have NaN or Inf {what}, first at vertex "
                            f"{int(np.nonzero(bad)[0][0])}")
    length = np.linalg.norm(nrm, axis=1)
    if (length == 0).any():
        raise DataError(f"{path}: {int((length == 0).sum())} vertices have zero-length normals")
    nrm = nrm / length[:, None]
    return PointCloud(torch.as_tensor(pts, dtype=dtype), torch.as_tensor(nrm, dtype=dtype), path.stem)


@dataclasses.dataclass
class PlainCloud:
    """A point cloud as scanners and photogrammetry tools write it.

    Attributes:
        points: ``[N,3]`` float64 positions. normals: ``[N,3]`` unit normals, or ``None`` when the file has
            none (or only zero-length ones). colours: ``[N,3]`` float64 in [0, 1], or ``None``.
    """

    points: torch.Tensor
    normals: torch.Tensor | None
    colours: torch.Tensor | None


def read_vertex_element(path: str | Path) -> tuple[Path, PlyElement, set[str]]:
    """The ``vertex`` element of the PLY at ``path`` and its property names, after the header check; a missing
    or unreadable file raises a one-line error naming it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: no PLY file at {path}")
    check_ply_header(path)
    try:
        v = PlyData.read(str(path))["vertex"]
    except Exception as exc:  # noqa: BLE001 - plyfile's parse errors do not name the file
        raise DataError(f"{path}: not a readable PLY file with a 'vertex' element: {exc}") from exc
    return path, v, set(v.data.dtype.names)


def read_point_ply(path: str | Path) -> PlainCloud:
    """Read ``x y z`` and, where present, ``nx ny nz`` and ``red green blue`` (8- or 16-bit integers, or floats in
    [0, 1]) from a PLY's ``vertex`` element. Bad files raise a one-line :class:`DataError` naming them."""
    path, v, names = read_vertex_element(path)
    if not {"x", "y", "z"} <= names:
        raise DataError(f"{path}: missing vertex properties x y z")
    if v.count == 0:
        raise DataError(f"{path}: the PLY has zero vertices")

    def cols(keys: tuple[str, ...]) -> np.ndarray:
        try:
            arr = np.stack([np.asarray(v[k], np.float64) for k in keys], 1)
        except (TypeError, ValueError) as exc:
            raise DataError(f"{path}: vertex properties {' '.join(keys)} must be numeric scalars: {exc}") from None
        bad = ~np.isfinite(arr).all(1)
        if bad.any():
            raise DataError(f"{path}: {int(bad.sum())} vertices have NaN or Inf {' '.join(keys)}, first at vertex "
                            f"{int(np.nonzero(bad)[0][0])}")
        return arr

    points = torch.from_numpy(cols(("x", "y", "z")))
    normals = colours = None
    if {"nx", "ny", "nz"} <= names:
        n = cols(("nx", "ny", "nz"))
        length = np.linalg.norm(n, axis=1, keepdims=True)
        if (length > 0).all():
            normals = torch.from_numpy(n / length)
    if {"red", "green", "blue"} <= names:
        rgb = cols(("red", "green", "blue"))
        kind = v.data.dtype["red"]
        scale = float(np.iinfo(kind).max) if np.issubdtype(kind, np.integer) else 1.0
        colours = torch.from_numpy(np.clip(rgb / scale, 0.0, 1.0))
    return PlainCloud(points, normals, colours)


def load_dss_shape(name: str, root: str | Path | None = None, dtype: torch.dtype = torch.float32) -> PointCloud:
    """Load DSS shape ``name`` (one of :data:`DSS_SHAPES`) from ``root/dss_pointclouds``.

    ``root`` defaults to :func:`default_data_root`.
    """
    if name not in DSS_SHAPES:
        raise ValueError(f"shape: unknown DSS shape {name!r}; expected one of {sorted(DSS_SHAPES)}")
    path = (Path(root) if root else default_data_root()) / "dss_pointclouds" / DSS_SHAPES[name]
    if not path.is_file():
        raise FileNotFoundError(f"no DSS point cloud at {path}; download them with `nsplat data fetch dss` "
                                f"(into $NSPLAT_DATA, else ~/.local/share/nsplat)")
    pc = read_oriented_ply(path, dtype=dtype)
    pc.name = name
    return pc


def check_shape(shape: str) -> None:
    """Raise :class:`~nsplat.config.ConfigError` unless ``shape`` is a DSS name or a path ending in ``.ply``."""
    if not isinstance(shape, str) or not (shape in DSS_SHAPES or shape.lower().endswith(".ply")):
        raise ConfigError(f"data.shape: expected one of {sorted(DSS_SHAPES)} or the path of a .ply file, "
                          f"got {shape!r}")


def estimate_normals(points: torch.Tensor, k: int = 12) -> torch.Tensor:
    """Unit normals ``[N,3]`` of ``points [N,3]``, consistently oriented.

    Each normal is the direction of least variance of the point's ``k`` nearest neighbours (PCA). Orientation is
    propagated along a minimum spanning tree of the neighbour graph weighted by ``1 - |n_i · n_j|`` (Hoppe et al.
    1992), starting from the point farthest from the centroid, whose normal is turned away from the centroid; each
    connected component is seeded the same way. Thin parts closer than the neighbourhood size can still flip.
    """
    pts = points.detach().cpu().double().numpy()
    n = pts.shape[0]
    if n < 4:
        raise DataError(f"points: estimating normals needs at least 4 points, got {n}")
    k = min(k, n - 1)
    _, nbr = cKDTree(pts).query(pts, k=k + 1)
    local = pts[nbr] - pts[nbr].mean(axis=1, keepdims=True)            # [N,k+1,3]
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))
    normals = vecs[:, :, 0]                                              # smallest eigenvalue's vector
    rows = np.repeat(np.arange(n), k)
    cols = nbr[:, 1:].reshape(-1)
    weight = 1.0 - np.abs((normals[rows] * normals[cols]).sum(1)) + 1e-6
    tree = minimum_spanning_tree(coo_matrix((weight, (rows, cols)), shape=(n, n)).tocsr())
    tree = tree + tree.T
    centre = pts.mean(0)
    done = np.zeros(n, dtype=bool)
    for seed in np.argsort(-np.linalg.norm(pts - centre, axis=1)):
        if done[seed]:
            continue
        if normals[seed] @ (pts[seed] - centre) < 0:
            normals[seed] = -normals[seed]
        order, parent = breadth_first_order(tree, seed, directed=False)
        for i in order[1:]:
            if normals[i] @ normals[parent[i]] < 0:
                normals[i] = -normals[i]
        done[order] = True
    return torch.as_tensor(normals, dtype=points.dtype)


def load_shape(shape: str, root: str | Path | None = None, dtype: torch.dtype = torch.float32) -> PointCloud:
    """The ground-truth cloud ``shape``: a DSS name (:func:`load_dss_shape`, from ``root``) or a PLY path
    (:func:`read_point_ply`; normals from the file, else :func:`estimate_normals`).

    Raises:
        ConfigError: ``shape`` is neither. FileNotFoundError / DataError: a missing or bad file, named.
    """
    check_shape(shape)
    if shape in DSS_SHAPES:
        return load_dss_shape(shape, root, dtype=dtype)
    cloud = read_point_ply(shape)
    points = cloud.points.to(dtype)
    if points.shape[0] < 4:
        raise DataError(f"{shape}: a shape needs at least 4 points, got {points.shape[0]}")
    extent = (points.max(0).values - points.min(0).values).norm()
    if not float(extent) > 0:
        raise DataError(f"{shape}: every point is at the same position")
    normals = cloud.normals.to(dtype) if cloud.normals is not None else estimate_normals(points)
    return PointCloud(points, normals, Path(shape).stem)

"""A learnable set of oriented surfels (docs/method.md), allocating only what its config asks for.

A :class:`SurfelScene` stores, per point ``k``: position ``p_k`` (3), normal ``n_k`` (3, stored raw and
normalised by the op), log tangent std-devs ``log s_k`` (2), opacity logit (1) and features ``f_k`` (C).
:class:`SceneConfig` says which of them exist and which are learnable:

* ``learn`` lists the learnable attributes (``nn.Parameter``); the others are buffers (frozen, saved).
* ``opacity: float`` makes opacity a constant (nothing allocated); ``None`` allocates a per-point logit.
* ``scale: float`` makes the tangent std-dev a constant isotropic value (nothing allocated); ``None``
  allocates per-point log-scales ``[N, 2]``.

The properties :attr:`~SurfelScene.means`, :attr:`~SurfelScene.normals`, :attr:`~SurfelScene.scales`,
:attr:`~SurfelScene.opacities` and :attr:`~SurfelScene.features` always return op-ready tensors
(constants are expanded views), so callers never branch on the config.
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Iterable, Literal, Mapping

import numpy as np
import torch
from plyfile import PlyData, PlyElement
from scipy.spatial import cKDTree
from torch import nn

from nsplat.config import require, require_fields
from nsplat.data.pointclouds import read_vertex_element
from nsplat.errors import DataError
from nsplat.points import gather_rows, reset_rows, select_rows

log = logging.getLogger(__name__)

#: Attribute names, in storage order. ``means``/``normals`` always exist.
ATTRIBUTES = ("means", "normals", "scales", "opacities", "features")
_STORAGE = {"means": "_means", "normals": "_normals", "scales": "_log_scales",
            "opacities": "_opacity_logits", "features": "_features"}
_EPS = 1e-6


@dataclasses.dataclass
class SceneConfig:
    """Which per-point attributes a scene has and which are learned.

    Attributes:
        channels: feature channels C per point (3 for RGB albedo; >= 1).
        learn: learnable attributes, a subset of ``means, normals, scales, opacities, features``.
        opacity: constant opacity in (0, 1] (nothing allocated), or ``None`` for a per-point logit.
        scale: constant isotropic tangent std-dev (world units, > 0; nothing allocated), or ``None``
            for per-point log-scales ``[N, 2]``.
        feature_activation: ``identity`` (features stored as is) or ``sigmoid`` (stored as logits,
            returned in (0, 1)).
    """

    channels: int = 3
    learn: list[str] = dataclasses.field(default_factory=lambda: ["means", "normals", "scales", "features"])
    opacity: float | None = 1.0
    scale: float | None = None
    feature_activation: Literal["identity", "sigmoid"] = "identity"

    def __post_init__(self) -> None:
        require_fields(self, channels=">=1", opacity="prob", scale=">0")
        require(all(a in ATTRIBUTES for a in self.learn), "learn", f"a subset of {list(ATTRIBUTES)}", self.learn)
        require(len(set(self.learn)) == len(self.learn), "learn", "no duplicate entries", self.learn)
        require(self.opacity is None or "opacities" not in self.learn, "learn",
                "no 'opacities' with a constant opacity (set opacity: null to allocate per-point opacities)",
                self.learn)
        require(self.scale is None or "scales" not in self.learn, "learn",
                "no 'scales' with a constant scale (set scale: null to allocate per-point scales)", self.learn)

    def allocated(self) -> tuple[str, ...]:
        """Names of the attributes stored per point under this config."""
        out = ["means", "normals"]
        if self.scale is None:
            out.append("scales")
        if self.opacity is None:
            out.append("opacities")
        out.append("features")
        return tuple(out)


def knn_spacing(points: np.ndarray | torch.Tensor, k: int = 3) -> np.ndarray:
    """Mean distance of each point ``[N,3]`` to its ``k`` nearest neighbours: ``[N]`` (float64)."""
    pts = points.detach().cpu().double().numpy() if isinstance(points, torch.Tensor) else np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points: expected shape [N, 3], got {list(pts.shape)}")
    if pts.shape[0] < 2:
        raise ValueError(f"points: need at least 2 points for a neighbour spacing, got {pts.shape[0]}")
    k = min(k, pts.shape[0] - 1)
    dist, _ = cKDTree(pts).query(pts, k=k + 1)
    return dist[:, 1:].mean(axis=1)


def _logit(p: torch.Tensor) -> torch.Tensor:
    p = p.clamp(_EPS, 1.0 - _EPS)
    return torch.log(p) - torch.log1p(-p)


class SurfelScene(nn.Module):
    """Per-point surfel attributes (see the module docstring); ``N`` points, ``C`` feature channels.

    Build with :meth:`from_points` (or :meth:`load_ply`); a scene with the same config and point count
    can load another's ``state_dict``.
    """

    def __init__(self, cfg: SceneConfig, num_points: int, dtype: torch.dtype = torch.float32,
                 device: str | torch.device = "cpu") -> None:
        """Allocate an (all-zero, unit-normal) scene of ``num_points`` points under ``cfg``."""
        super().__init__()
        if num_points < 1:
            raise ValueError(f"num_points: expected >= 1, got {num_points}")
        self.cfg = cfg
        n, C = num_points, cfg.channels
        shapes = {"means": (n, 3), "normals": (n, 3), "scales": (n, 2), "opacities": (n,), "features": (n, C)}
        for name in cfg.allocated():
            t = torch.zeros(shapes[name], dtype=dtype, device=device)
            if name == "normals":
                t[:, 2] = 1.0
            if name in cfg.learn:
                self.register_parameter(_STORAGE[name], nn.Parameter(t))
            else:
                self.register_buffer(_STORAGE[name], t)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_points(cls, cfg: SceneConfig, means: torch.Tensor, normals: torch.Tensor, *,
                    scales: torch.Tensor | float | None = None, opacities: torch.Tensor | float | None = None,
                    features: torch.Tensor | float | None = None, scale_factor: float = 1.0) -> "SurfelScene":
        """A scene from op-ready values.

        Args:
            means ``[N,3]``, normals ``[N,3]``: positions and normals (normals are normalised).
            scales: ``[N,2]``/``[N]`` positive std-devs or a number; default: ``scale_factor`` times the
                mean distance to the 3 nearest neighbours (isotropic). Ignored when ``cfg.scale`` is set.
            opacities: ``[N]`` in (0, 1) or a number; default 0.5. Ignored when ``cfg.opacity`` is set.
            features: ``[N,C]`` or a number (all channels); default 0.5.
        """
        if means.dim() != 2 or means.shape[1] != 3:
            raise ValueError(f"means: expected shape [N, 3], got {list(means.shape)}")
        if normals.shape != means.shape:
            raise ValueError(f"normals: expected shape {list(means.shape)}, got {list(normals.shape)}")
        n = means.shape[0]
        scene = cls(cfg, n, dtype=means.dtype, device=means.device)
        values: dict[str, torch.Tensor] = {"means": means, "normals": normals}
        if cfg.scale is None:
            if scales is None:
                sp = torch.as_tensor(knn_spacing(means), dtype=means.dtype, device=means.device)
                scales = (scale_factor * sp)[:, None].expand(n, 2)
            values["scales"] = _as_rows(scales, (n, 2), "scales", means)
        if cfg.opacity is None:
            values["opacities"] = _as_rows(0.5 if opacities is None else opacities, (n,), "opacities", means)
        values["features"] = _as_rows(0.5 if features is None else features, (n, cfg.channels), "features", means)
        scene.set_values(values)
        return scene

    # ------------------------------------------------------------------ op-ready views
    @property
    def num_points(self) -> int:
        """Number of points N."""
        return self._means.shape[0]

    @property
    def means(self) -> torch.Tensor:
        """``[N,3]`` world positions."""
        return self._means

    @property
    def normals(self) -> torch.Tensor:
        """``[N,3]`` unit normals."""
        return nn.functional.normalize(self._normals, dim=-1)

    @property
    def scales(self) -> torch.Tensor:
        """``[N,2]`` positive tangent std-devs (world units)."""
        if self.cfg.scale is not None:
            return self._means.new_full((1, 1), self.cfg.scale).expand(self.num_points, 2)
        return torch.exp(self._log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        """``[N]`` opacities in (0, 1] (the constant when ``cfg.opacity`` is set)."""
        if self.cfg.opacity is not None:
            return self._means.new_full((1,), self.cfg.opacity).expand(self.num_points)
        return torch.sigmoid(self._opacity_logits)

    @property
    def features(self) -> torch.Tensor:
        """``[N,C]`` features (after ``cfg.feature_activation``)."""
        if self.cfg.feature_activation == "sigmoid":
            return torch.sigmoid(self._features)
        return self._features

    def tensor(self, name: str) -> torch.Tensor:
        """The stored (raw) tensor of attribute ``name`` (raises ``KeyError`` if not allocated)."""
        if name not in self.cfg.allocated():
            raise KeyError(f"attribute {name!r} is not allocated under this scene config "
                           f"(allocated: {list(self.cfg.allocated())})")
        return getattr(self, _STORAGE[name])

    # ------------------------------------------------------------------ raw <-> op-ready
    def _encode(self, name: str, value: torch.Tensor) -> torch.Tensor:
        if name == "normals":
            return nn.functional.normalize(value, dim=-1)
        if name == "scales":
            if bool((value <= 0).any()):
                raise ValueError("scales: expected all values > 0")
            return torch.log(value)
        if name == "opacities":
            return _logit(value)
        if name == "features" and self.cfg.feature_activation == "sigmoid":
            return _logit(value)
        return value

    @torch.no_grad()
    def set_values(self, values: Mapping[str, torch.Tensor], index: torch.Tensor | None = None) -> None:
        """Write op-ready ``values`` (name → tensor) into all rows or the rows ``index [M]``.

        Names must be allocated attributes; constants (``cfg.opacity``/``cfg.scale``) cannot be set.
        """
        for name, value in values.items():
            raw = self.tensor(name)
            enc = self._encode(name, value.to(dtype=raw.dtype, device=raw.device))
            if index is None:
                if enc.shape != raw.shape:
                    raise ValueError(f"{name}: expected shape {list(raw.shape)}, got {list(enc.shape)}")
                raw.copy_(enc)
            else:
                raw[index] = enc

    @torch.no_grad()
    def replace(self, index: torch.Tensor, values: Mapping[str, torch.Tensor],
                optimizer: torch.optim.Optimizer | None = None) -> None:
        """Replace rows ``index [M]`` (long) by op-ready ``values`` and reset their optimiser state.

        Attributes not in ``values`` keep their rows. For every learnable tensor, the Adam moments
        (``exp_avg``, ``exp_avg_sq``, and ``max_exp_avg_sq`` when present) of the replaced rows are
        zeroed, so stale momentum does not push the moved points (the per-tensor ``step`` is shared
        and kept).
        """
        index = torch.as_tensor(index, dtype=torch.long, device=self._means.device)
        self.set_values(values, index)
        if optimizer is not None:
            reset_rows([optimizer], [self.tensor(name) for name in self.cfg.learn], index)

    @torch.no_grad()
    def select(self, keep: torch.Tensor, optimizers: Iterable[torch.optim.Optimizer] = ()) -> "SurfelScene":
        """A new scene of the rows ``keep [N]`` (bool); ``optimizers`` are moved to its parameters with
        their state sliced (:func:`nsplat.points.select_rows`)."""
        new = SurfelScene(self.cfg, int(keep.sum()), dtype=self._means.dtype, device=self._means.device)
        new.load_state_dict({k: v[keep] for k, v in self.state_dict().items()})
        select_rows(optimizers, {self.tensor(n): new.tensor(n) for n in self.cfg.learn}, keep)
        return new

    @torch.no_grad()
    def gather_(self, index: torch.Tensor, optimizers: Iterable[torch.optim.Optimizer] = (),
                fresh: torch.Tensor | None = None) -> None:
        """Rebuild the point set in place: new row ``i`` is old row ``index[i]`` (repeats allowed).

        Learnable tensors become new ``nn.Parameter`` objects; ``optimizers`` are moved to them with
        their per-row state gathered and zeroed on the ``fresh`` rows (:func:`nsplat.points.gather_rows`).

        Args:
            index: ``[N']`` long old-row indices. optimizers: optimisers holding this scene's parameters.
            fresh: ``[N']`` bool, new rows whose optimiser moments restart from zero.
        """
        index = torch.as_tensor(index, dtype=torch.long, device=self._means.device)
        replaced = {}
        for name in self.cfg.allocated():
            old = self.tensor(name)
            data = old.detach()[index].clone()
            if isinstance(old, nn.Parameter):
                new = nn.Parameter(data, requires_grad=old.requires_grad)
                setattr(self, _STORAGE[name], new)
                replaced[old] = new
            else:
                setattr(self, _STORAGE[name], data)
        gather_rows(optimizers, replaced, index, fresh)

    def resize_(self, num_points: int) -> None:
        """Resize to ``num_points`` rows (contents unspecified; e.g. before loading a checkpoint of a
        densified scene). Call before any optimiser is built over the scene."""
        self.gather_(torch.zeros(num_points, dtype=torch.long, device=self._means.device))

    # ------------------------------------------------------------------ optimiser
    def param_groups(self, lrs: Mapping[str, float]) -> list[dict]:
        """Optimiser parameter groups, one per learnable attribute: ``{"params", "lr", "name"}``.

        ``lrs`` maps attribute names (and optionally ``"default"``) to learning rates; entries for
        frozen or unallocated attributes are ignored. A learnable attribute without a rate (and no
        ``default``) or an unknown name raises ``ValueError``.
        """
        unknown = [k for k in lrs if k not in ATTRIBUTES and k != "default"]
        if unknown:
            raise ValueError(f"lrs: unknown attribute(s) {unknown}; expected names from {list(ATTRIBUTES)} "
                             "or 'default'")
        groups = []
        for name in self.cfg.learn:
            lr = lrs.get(name, lrs.get("default"))
            if lr is None:
                raise ValueError(f"lrs: no learning rate for learnable attribute {name!r} (and no 'default')")
            groups.append({"params": [self.tensor(name)], "lr": float(lr), "name": name})
        return groups

    # ------------------------------------------------------------------ PLY
    def save_ply(self, path: str | Path) -> None:
        """Write the stored attributes as a binary PLY vertex element.

        Properties: ``x y z nx ny nz`` (unit normals), ``scale_0 scale_1`` (log std-devs, if allocated),
        ``opacity`` (logit, if allocated), ``f_0 … f_{C-1}`` (raw stored features).
        """
        cols: list[tuple[str, np.ndarray]] = []
        means = self._means.detach().cpu().numpy()
        normals = self.normals.detach().cpu().numpy()
        cols += [(n, means[:, i]) for i, n in enumerate("xyz")]
        cols += [(f"n{a}", normals[:, i]) for i, a in enumerate("xyz")]
        if self.cfg.scale is None:
            ls = self._log_scales.detach().cpu().numpy()
            cols += [("scale_0", ls[:, 0]), ("scale_1", ls[:, 1])]
        if self.cfg.opacity is None:
            cols.append(("opacity", self._opacity_logits.detach().cpu().numpy()))
        f = self._features.detach().cpu().numpy()
        cols += [(f"f_{c}", f[:, c]) for c in range(f.shape[1])]
        arr = np.empty(self.num_points, dtype=[(n, "f4") for n, _ in cols])
        for n, v in cols:
            arr[n] = v
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        PlyData([PlyElement.describe(arr, "vertex")], text=False).write(str(path))

    @classmethod
    def load_ply(cls, path: str | Path, cfg: SceneConfig, dtype: torch.dtype = torch.float32,
                 device: str | torch.device = "cpu") -> "SurfelScene":
        """Read a PLY written by :meth:`save_ply`; every attribute ``cfg`` allocates must be present."""
        path, vertex, names = read_vertex_element(path)
        if vertex.count == 0:
            raise DataError(f"{path}: the PLY has zero vertices")

        def cols(keys: list[str], what: str) -> torch.Tensor:
            missing = [k for k in keys if k not in names]
            if missing:
                raise DataError(f"{path}: missing PLY properties {missing} needed for scene attribute {what!r}")
            try:
                arr = np.stack([np.asarray(vertex[k], np.float64) for k in keys], 1)
            except (TypeError, ValueError) as exc:
                raise DataError(f"{path}: PLY properties {keys} must be numeric scalars: {exc}") from None
            bad = ~np.isfinite(arr).all(1)
            if bad.any():
                raise DataError(f"{path}: {int(bad.sum())} vertices have NaN or Inf {what}, first at vertex "
                                f"{int(np.nonzero(bad)[0][0])}")
            return torch.as_tensor(arr, dtype=dtype)

        scene = cls(cfg, vertex.count, dtype=dtype, device=device)
        raw = {"means": cols(list("xyz"), "means"), "normals": cols(["nx", "ny", "nz"], "normals"),
               "features": cols([f"f_{c}" for c in range(cfg.channels)], "features")}
        if cfg.scale is None:
            raw["scales"] = cols(["scale_0", "scale_1"], "scales")
        if cfg.opacity is None:
            raw["opacities"] = cols(["opacity"], "opacities")[:, 0]
        with torch.no_grad():
            for name, value in raw.items():
                scene.tensor(name).copy_(value.to(device))
        return scene


def _as_rows(value: torch.Tensor | float, shape: tuple[int, ...], name: str, like: torch.Tensor) -> torch.Tensor:
    """Broadcast a number, ``[N]`` or full tensor to ``shape`` (dtype/device of ``like``)."""
    t = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if t.dim() == 1 and len(shape) == 2 and t.shape[0] == shape[0]:
        t = t[:, None]
    try:
        return t.expand(shape).clone()
    except RuntimeError as exc:
        raise ValueError(f"{name}: cannot broadcast shape {list(t.shape)} to {list(shape)}") from exc

"""Per-point mutation with optimiser state: the one place that rewrites Adam state row by row.

Three operations cover the framework's needs: :func:`reset_rows` (points moved in place, e.g. the
fitter's repositioning: their moments restart from zero), :func:`gather_rows` (the point set is
rebuilt from rows of the old one, with repeats: densification's clones and splits, pruning; the new
parameters' moments are the gathered old rows, zero for rows marked fresh) and :func:`select_rows`
(points removed, e.g. refine's outlier filter: the special case of a gather without repeats).
"""
from __future__ import annotations

from typing import Iterable, Mapping

import torch
from torch import nn

#: Adam state entries that hold one value per parameter element (the per-tensor ``step`` is shared).
_MOMENTS = ("exp_avg", "exp_avg_sq", "max_exp_avg_sq")


@torch.no_grad()
def reset_rows(optimizers: Iterable[torch.optim.Optimizer], params: Iterable[nn.Parameter],
               index: torch.Tensor) -> None:
    """Zero the Adam moments of rows ``index [M]`` (long) of ``params`` in every optimiser holding them."""
    for opt in optimizers:
        for p in params:
            state = opt.state.get(p)
            for key in _MOMENTS:
                buf = state.get(key) if state else None
                if isinstance(buf, torch.Tensor) and buf.shape == p.shape:
                    buf[index] = 0


@torch.no_grad()
def gather_rows(optimizers: Iterable[torch.optim.Optimizer], replaced: Mapping[nn.Parameter, nn.Parameter],
                index: torch.Tensor, fresh: torch.Tensor | None = None) -> None:
    """Point the optimisers at new parameters whose row ``i`` is row ``index[i]`` of the old ones.

    Per-element state (Adam moments) is gathered the same way, then zeroed on the ``fresh`` rows (new
    points start without momentum); per-tensor state (``step``) is kept.

    Args:
        optimizers: optimisers whose param groups may hold old parameters.
        replaced: old parameter ``[N,...]`` → new parameter ``[N',...]``.
        index: ``[N']`` long, the old row of every new row (repeats allowed).
        fresh: ``[N']`` bool, rows whose moments restart from zero (``None``: none).
    """
    for opt in optimizers:
        for group in opt.param_groups:
            for i, p_old in enumerate(group["params"]):
                p_new = replaced.get(p_old)
                if p_new is None:
                    continue
                if p_new.shape[1:] != p_old.shape[1:] or p_new.shape[0] != index.shape[0]:
                    raise ValueError(f"gather_rows: new parameter {list(p_new.shape)} does not hold "
                                     f"{index.shape[0]} rows of {list(p_old.shape)}")
                group["params"][i] = p_new
                st = opt.state.pop(p_old, None)
                if not st:
                    continue
                new_state = {}
                for k, v in st.items():
                    if isinstance(v, torch.Tensor) and v.shape == p_old.shape:
                        v = v[index]
                        if fresh is not None:
                            v[fresh] = 0
                    new_state[k] = v
                opt.state[p_new] = new_state


@torch.no_grad()
def select_rows(optimizers: Iterable[torch.optim.Optimizer], replaced: Mapping[nn.Parameter, nn.Parameter],
                keep: torch.Tensor) -> None:
    """Point the optimisers at new parameters holding rows ``keep`` of the old ones, slicing their state.

    Args:
        optimizers: optimisers whose param groups may hold old parameters.
        replaced: old parameter ``[N,...]`` → new parameter ``[N',...]`` (the kept rows).
        keep: ``[N]`` bool or ``[N']`` long, the kept rows.
    """
    index = keep.nonzero().squeeze(1) if keep.dtype == torch.bool else keep
    gather_rows(optimizers, replaced, index)

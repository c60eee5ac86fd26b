"""Per-point mutation with optimiser state: the one place that rewrites Adam state row by row.

Two operations cover the framework's needs: :func:`reset_rows` (points moved in place, e.g. the
fitter's repositioning: their moments restart from zero) and :func:`select_rows` (points removed, e.g.
refine's outlier filter: parameters are replaced by their kept rows and so are their moments).
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
def select_rows(optimizers: Iterable[torch.optim.Optimizer], replaced: Mapping[nn.Parameter, nn.Parameter],
                keep: torch.Tensor) -> None:
    """Point the optimisers at new parameters holding rows ``keep`` of the old ones, slicing their state.

    Args:
        optimizers: optimisers whose param groups may hold old parameters.
        replaced: old parameter ``[N,...]`` → new parameter ``[N',...]`` (the kept rows).
        keep: ``[N]`` bool or ``[N']`` long, the kept rows.
    """
    for opt in optimizers:
        for group in opt.param_groups:
            for i, p_old in enumerate(group["params"]):
                p_new = replaced.get(p_old)
                if p_new is None:
                    continue
                group["params"][i] = p_new
                st = opt.state.pop(p_old, None)
                if st:
                    opt.state[p_new] = {k: (v[keep] if isinstance(v, torch.Tensor) and v.shape == p_old.shape else v)
                                        for k, v in st.items()}

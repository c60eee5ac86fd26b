"""The surfel fitter (:mod:`nsplat.fitting.fitter`) and its optional strategies.

* :mod:`~nsplat.fitting.fitter` — :class:`FitConfig`, :func:`fit`, :func:`build`: the algorithm;
* :mod:`~nsplat.fitting.strategy` — :class:`Strategy`, the interface the optional parts plug into;
* :mod:`~nsplat.fitting.reposition`, :mod:`~nsplat.fitting.densify`, :mod:`~nsplat.fitting.mask_loss` — the
  strategies, each with its config section (``reposition``, ``densify``, ``mask_loss`` of :class:`FitConfig`).
"""
from nsplat.fitting.densify import DensifyConfig
from nsplat.fitting.fitter import FitConfig, build, fit
from nsplat.fitting.mask_loss import MaskLossConfig
from nsplat.fitting.reposition import RepositionConfig, point_contributions
from nsplat.fitting.strategy import FitState, Strategy, ViewRender

__all__ = ["DensifyConfig", "FitConfig", "FitState", "MaskLossConfig", "RepositionConfig", "Strategy", "ViewRender",
           "build", "fit", "point_contributions"]

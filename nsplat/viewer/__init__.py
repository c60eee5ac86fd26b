"""Looking at trained runs: the render function, the viser web viewer and the live training view.

* :mod:`nsplat.viewer.model` — :class:`ViewModel` and :func:`render_view` (camera → images).
* :mod:`nsplat.viewer.runs` — a run folder (any task) or live training state → :class:`ViewModel`.
* :mod:`nsplat.viewer.server` — the viser server (``python train.py view --run DIR``).
* :mod:`nsplat.viewer.live` — the training loops' hook (``python train.py ... viewer=true``).
* :mod:`nsplat.viewer.commands` — the ``view`` / ``export`` sub-commands.

viser is imported only when a server starts.
"""
from nsplat.viewer.model import RenderSettings, TrainingCameras, ViewImages, ViewModel, render_view, to_display

__all__ = ["RenderSettings", "TrainingCameras", "ViewImages", "ViewModel", "render_view", "to_display"]

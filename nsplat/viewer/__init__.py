"""Looking at trained runs: the render function, the viser web viewer and the live training view.

* :mod:`nsplat.viewer.config` — :class:`ViewerConfig`, the ``viewer.<key>`` settings of both commands.
* :mod:`nsplat.viewer.model` — :func:`render_view` (a :class:`ViewModel` and a camera → images).
* :mod:`nsplat.viewer.runs` — a run folder (any task) → :class:`ViewModel`, through the task's ``view``.
* :mod:`nsplat.viewer.server` — the viser server (``python train.py view --run DIR [viewer.<key>=…]``).
* :mod:`nsplat.viewer.live` — the training loops' hook (``python train.py ... viewer=true``).
* :mod:`nsplat.viewer.commands` — the ``view`` / ``export`` sub-commands.

The :class:`ViewModel` itself is built by the tasks (:mod:`nsplat.render.view_model`): the viewer depends on
the tasks, never the reverse. viser is imported only when a server starts.
"""
from nsplat.render.view_model import TrainingCameras, ViewModel
from nsplat.viewer.config import ViewerConfig
from nsplat.viewer.model import RenderSettings, ViewImages, render_view, to_display

__all__ = ["RenderSettings", "TrainingCameras", "ViewImages", "ViewModel", "ViewerConfig", "render_view", "to_display"]

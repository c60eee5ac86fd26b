"""Rendering and showing a scene: from the learnable surfels (:class:`nsplat.scene.SurfelScene`) to images.

* :mod:`~nsplat.render.renderer` — the gateway every task renders through (:class:`RenderConfig`,
  :func:`render`): the unbiased Poisson-sampling op (:mod:`nsplat.ops`) or the truncated baseline;
* :mod:`~nsplat.render.truncated` — the 3σ-truncated, exactly composited baseline renderer;
* :mod:`~nsplat.render.shading`, :mod:`~nsplat.render.sh` — Lambert shading and spherical harmonics (view
  colour, irradiance);
* :mod:`~nsplat.render.view_model` — a trained scene as the viewer and the exporters see it;
* :mod:`~nsplat.render.camera_paths`, :mod:`~nsplat.render.video` — orbit/spiral/interpolated camera paths and
  the videos rendered along them.
"""

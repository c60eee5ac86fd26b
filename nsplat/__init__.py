"""nsplat — neural point-based rendering on differentiable surface splatting via Poisson sampling.

The rooms, lowest first (a room imports only from rooms below it; tests/test_layout.py checks it):

* ``nsplat.ops`` (the splatting operator) and ``nsplat.models`` (the U-Net shader, the PatchGAN, their losses);
* the vocabulary every room shares, at this level: :mod:`nsplat.errors`, :mod:`nsplat.config`,
  :mod:`nsplat.cameras`, :mod:`nsplat.points`;
* :mod:`nsplat.data` — data sets, captures and the posed-views type;
* :mod:`nsplat.scene` — the learnable surfels;
* :mod:`nsplat.render` (renderers, shading, cameras paths, videos), :mod:`nsplat.evaluation` (protocols, metrics,
  sheets), :mod:`nsplat.run` (engine, run folders, checkpoints, distribution, result lines);
* :mod:`nsplat.gaussians` (3DGS interchange) and :mod:`nsplat.fitting` (the surfel fitter);
* :mod:`nsplat.tasks` (neural rendering, shape reconstruction, refinement, demo);
* :mod:`nsplat.viewer` (the web viewer, exports of runs);
* :mod:`nsplat.cli` — the command line, the one module that sees every room.
"""
__version__ = "0.1.0"

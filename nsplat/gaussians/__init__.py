"""3D Gaussian Splatting interchange: surfels as 3DGS Gaussians and back.

* :mod:`~nsplat.gaussians.kernel` — a surfel's footprint as a flat 3D Gaussian (the covariance conventions);
* :mod:`~nsplat.gaussians.ply` — the 3DGS PLY file (read and write);
* :mod:`~nsplat.gaussians.raster` — a reference 3DGS rasteriser (what a 3DGS viewer shows);
* :mod:`~nsplat.gaussians.fit` — the short fit that makes the exported Gaussians match the surfel renders;
* :mod:`~nsplat.gaussians.export` — ``train.py export`` (classic and antialiased 3DGS files).
"""

"""Measuring results.

* :mod:`~nsplat.evaluation.protocol` — the held-out image protocol (background, masks, which views);
* :mod:`~nsplat.evaluation.image_metrics` — PSNR, SSIM, LPIPS of images;
* :mod:`~nsplat.evaluation.shape_metrics` — Chamfer and normal distances between point clouds (Table 1);
* :mod:`~nsplat.evaluation.comparison_sheet` — side-by-side sheets of renders and references.
"""

"""Task ``refine``: camera-pose and scene refinement against posed RGB frames (paper §4, room scale).

Given reference frames, initial (perturbed) cameras and an initial surfel cloud, minimise the masked
L1 image loss over per-camera SE(3) corrections (:mod:`nsplat.tasks.refine.poses`, optional focal), the scene's
learnable attributes (:class:`nsplat.scene.SurfelScene`: positions, normals, scales, opacity, albedo;
each switchable by ``scene.learn``) and the shading (2nd-order SH, :mod:`nsplat.render.sh`; or plain albedo;
or Lambert with the paper's fixed lights, :mod:`nsplat.render.shading`). Poses and scene are optimised
jointly or alternately (``optim.schedule``); the outlier filter (:mod:`nsplat.tasks.refine.filtering`) removes
points whose accumulated photometric error is improbable.

Data sources: ``room`` (the synthetic benchmark of :mod:`nsplat.tasks.refine.room`, with ground-truth poses),
``nerf`` (NeRF-synthetic frames with ground-truth poses perturbed here, plus an initial cloud read
from a PLY written by :meth:`SurfelScene.save_ply`) and ``rgbd`` (a real RGB-D sequence with its SLAM or odometry
trajectory, :mod:`nsplat.data.rgbd`: the depth fused into the initial cloud or the SLAM system's PLY, a per-frame
exposure, an optional depth term and odometry prior, held-out frames scored after fitting their cameras to the
frozen scene, ATE / RPE against a ground truth; :mod:`~nsplat.tasks.refine.sequence`).

Every render goes through the gateway :func:`nsplat.render.renderer.render` (``render.renderer``: the sampled op,
the dense oracle or the truncated baseline).

Modules: :mod:`~nsplat.tasks.refine.config` (settings), :mod:`~nsplat.tasks.refine.data` (frames and initial scene),
:mod:`~nsplat.tasks.refine.model` (the refiner), :mod:`~nsplat.tasks.refine.optimisers` (loss, optimisers, schedule),
:mod:`~nsplat.tasks.refine.metrics`, :mod:`~nsplat.tasks.refine.commands` (the task contract; steps run on the
engine, :mod:`nsplat.run.engine`), :mod:`~nsplat.tasks.refine.poses`, :mod:`~nsplat.tasks.refine.exposure`,
:mod:`~nsplat.tasks.refine.filtering`, :mod:`~nsplat.tasks.refine.sequence` (scoring an RGB-D sequence) and
:mod:`~nsplat.tasks.refine.trajectory` (ATE / RPE).

Outputs in the run folder: ``tb/`` (TensorBoard), ``checkpoints/`` (atomic, exact resume),
``metrics_initial.json`` / ``metrics_final.json`` (pose errors, masked PSNR/SSIM, point count),
``scene.ply``, ``cameras.pt``, and ``renders/`` from the ``render`` command; for an RGB-D sequence
``metrics.json`` (before / after: train and held-out PSNR/SSIM/LPIPS, ATE, RPE, time, memory),
``trajectory.txt`` / ``trajectory_initial.txt`` (TUM format) and ``before_after/`` (sheets and videos).
"""
from nsplat.tasks.refine.commands import build, evaluate, render, restore, run, step, view
from nsplat.tasks.refine.config import Config
from nsplat.tasks.refine.data import load_data
from nsplat.tasks.refine.model import Refiner

__all__ = ["Config", "Refiner", "build", "evaluate", "load_data", "render", "restore", "run", "step", "view"]

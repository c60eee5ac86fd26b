"""Data: the posed-views type, path resolution, and the loaders that return it (NeRF-synthetic, the
procedural scene and its ray tracer, DSS point clouds, the synthetic room)."""
from nsplat.data.nerf_synthetic import load_split
from nsplat.data.procedural import ProceduralSpec, ensure_scene, generate, make_scene
from nsplat.data.views import PosedViews

__all__ = ["PosedViews", "load_split", "ProceduralSpec", "ensure_scene", "generate", "make_scene"]

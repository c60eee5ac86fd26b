"""Data: NeRF-synthetic loader, the procedural scene generator and its ray tracer."""
from nsplat.data.nerf_synthetic import Views, load_split
from nsplat.data.procedural import ProceduralSpec, ensure_scene, generate, make_scene

__all__ = ["Views", "load_split", "ProceduralSpec", "ensure_scene", "generate", "make_scene"]

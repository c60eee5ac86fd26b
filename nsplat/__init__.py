"""nsplat — neural point-based rendering on differentiable surface splatting via Poisson sampling.

Sub-packages: ``nsplat.ops`` (the splatting operator), ``nsplat.models`` (shader networks); modules
for cameras, scenes, data, tasks and checkpoints live beside this file.
"""
__version__ = "0.1.0"

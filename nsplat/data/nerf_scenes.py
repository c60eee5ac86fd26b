"""The eight NeRF-synthetic scenes by name: what ``nsplat data fetch`` unpacks from the NeRF authors' one archive
(``nerf_synthetic/<scene>``, :mod:`nsplat.data.fetch`) and which folder a config's ``data.scene`` reads.

``configs/nerf_synthetic.yaml`` trains any of them with ``data.scene: <name>``: with no ``data.root`` given, the
scene's 400-pixel copy ``$NSPLAT_DATA/nerf_synthetic/<scene>_400`` (``nsplat data fetch <scene> --resolution 400``)
is read whatever ``data.resolution`` the config trains at, since the loader resizes the images (lego.yaml trains
at 200² from it, lego_400.yaml at 400²); set ``data.root`` to read another copy (e.g. the 800² originals).
"""
from __future__ import annotations

from nsplat.config import require

#: The scenes of ``nerf_synthetic.zip``, each a folder ``nerf_synthetic/<scene>/`` in it.
NERF_SCENES = ("chair", "drums", "ficus", "hotdog", "lego", "materials", "mic", "ship")
#: The folder a config with ``data.scene`` and no ``data.root`` reads (``{scene}``: the scene's name).
SCENE_ROOT = "$NSPLAT_DATA/nerf_synthetic/{scene}_400"


def nerf_scene_root(source: str, scene: str | None, root: str | None) -> str | None:
    """A data config's ``root``: ``root`` when given, else for a NeRF-synthetic ``scene`` its :data:`SCENE_ROOT`.

    Raises :class:`~nsplat.config.FieldError` on ``scene`` (``data.scene`` once its section is prefixed) for a
    name not in :data:`NERF_SCENES` or a scene given with a ``source`` other than ``nerf_synthetic``.
    """
    if scene is None:
        return root
    require(scene in NERF_SCENES, "scene", f"a NeRF-synthetic scene, one of {', '.join(NERF_SCENES)}", scene)
    require(source == "nerf_synthetic", "scene", f"null with source {source} (a scene is a NeRF-synthetic one; "
                                                 f"set source: nerf_synthetic)", scene)
    return root or SCENE_ROOT.format(scene=scene)

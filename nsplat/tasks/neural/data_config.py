"""The ``data`` section of the ``neural`` task's config (:mod:`nsplat.tasks.neural.config`): the procedural scene,
a NeRF-synthetic folder or scene, or a capture of real photos."""
from __future__ import annotations

import dataclasses
from typing import Literal

from nsplat.config import require, require_fields
from nsplat.data.nerf_scenes import nerf_scene_root


@dataclasses.dataclass
class ProceduralConfig:
    """The embedded procedural scene (:class:`nsplat.data.ProceduralSpec`), generated on first use.

    Attributes:
        seed: scene seed. resolution: rendered image side (px). views: (train, val, test) counts.
        objects: number of objects. cache_dir: where scenes are generated (relative: to the repo root).
    """

    seed: int = 0
    resolution: int = 64
    views: tuple[int, int, int] = (40, 8, 8)
    objects: int = 4
    cache_dir: str = "data_cache"

    def __post_init__(self) -> None:
        require_fields(self, seed=">=0", resolution=">=1", views=">=1", objects=">=1")


@dataclasses.dataclass
class CaptureConfig:
    """A capture of real photos: a COLMAP folder (``data.source: colmap``) or a nerfstudio / instant-ngp
    ``transforms.json`` folder (``data.source: transforms``; :mod:`nsplat.tasks.neural.capture`, docs/capture.md).

    Attributes:
        downscale: photos at ``1/downscale`` (read from ``<images>_<downscale>/`` when it exists).
        holdout_every: every n-th image by name is the test split (8: the Mip-NeRF 360 / 3DGS convention).
        val_every: of the other images, every n-th from the (n/2)-th is the validation split (not trained on).
        images, sparse, masks: folders relative to ``data.root``: photos and model of a COLMAP capture (``sparse:
            null``: of the models in ``sparse/<k>``, the one with the most registered images, or ``sparse`` itself),
            coverage masks of either kind (``<masks>/<image name>.png`` or ``<masks>/<image name>``; ``null``: none).
        file: the JSON file of a ``transforms`` capture (``file_path`` relative to ``data.root``). cache_dir: folder
            of the undistorted photos (``null``: ``<root>/nsplat_undistorted``).
        normalize: move the world so the scene centre is the origin, z the cameras' up and their median distance to
            the centre ``radius`` (the units of the rates and ``geometry.bbox``; :mod:`nsplat.tasks.neural.frame`).
        near_far: near/far planes from the SfM depths (else from the background sphere; ``with_capture_render``).
    """

    downscale: int = 1
    holdout_every: int = 8
    val_every: int = 8
    images: str = "images"
    sparse: str | None = None
    masks: str | None = None
    normalize: bool = True
    radius: float = 3.2
    near_far: bool = True
    cache_dir: str | None = None
    file: str = "transforms.json"

    def __post_init__(self) -> None:
        require_fields(self, downscale=">=1", radius=">0", holdout_every=">=2", val_every=">=2")


#: Data sources that are captures of real photos (``data.capture`` applies).
CAPTURE_SOURCES = ("colmap", "transforms")


@dataclasses.dataclass
class DataConfig:
    """Where the posed images come from.

    Attributes:
        source: ``procedural`` (the embedded scene), ``nerf_synthetic`` (a folder at ``root``), ``colmap`` (a COLMAP
            capture at ``root``: ``sparse/<k>`` + ``images/``) or ``transforms`` (a nerfstudio or instant-ngp
            ``transforms.json`` folder at ``root``); the captures' settings in ``capture``.
        root: the scene folder (relative paths: to the repo root). scene: a NeRF-synthetic scene (``chair`` … ``ship``);
            ``root`` then defaults to its copy ``$NSPLAT_DATA/nerf_synthetic/<scene>_400``, whatever ``resolution``.
        resolution: image side after resizing (``null``: as stored). background: RGB under the RGBA images (white).
        train_limit, val_limit, test_limit: use only the first k frames of a split (``null``: all).
    """

    source: Literal["procedural", "nerf_synthetic", "colmap", "transforms"] = "procedural"
    root: str | None = None
    scene: str | None = None
    resolution: int | None = None
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    procedural: ProceduralConfig = dataclasses.field(default_factory=ProceduralConfig)
    capture: CaptureConfig = dataclasses.field(default_factory=CaptureConfig)
    train_limit: int | None = None
    val_limit: int | None = None
    test_limit: int | None = None

    def is_capture(self) -> bool:
        """Whether the source is a capture of real photos (``colmap`` or ``transforms``: ``capture`` applies)."""
        return self.source in CAPTURE_SOURCES

    def __post_init__(self) -> None:
        self.root = nerf_scene_root(self.source, self.scene, self.root)
        require(self.source == "procedural" or bool(self.root), "root", f"a folder with source {self.source}",
                self.root)
        require(not self.is_capture() or self.resolution is None, "resolution",
                f"null with source {self.source} (set capture.downscale)", self.resolution)
        require_fields(self, resolution=">=8", background="unit", train_limit=">=1", val_limit=">=1",
                       test_limit=">=1")

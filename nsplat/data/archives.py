"""Unpacking and checking the downloaded archives (:mod:`nsplat.data.fetch`): the folder of one NeRF-synthetic scene
from the NeRF authors' zip and the folder of one TUM RGB-D sequence from its ``.tgz``, with the structure checks
that stand in for the checksums their publishers do not give. Every failure is one line (:class:`FetchError`).
"""
from __future__ import annotations

import contextlib
import copy
import gzip
import json
import shutil
import tarfile
import zipfile
import zlib
from pathlib import Path, PurePosixPath

from tqdm import tqdm

from nsplat.data.nerf_synthetic import SPLITS
from nsplat.errors import DataError

#: Bytes read at a time.
CHUNK = 1 << 20
#: The lists of a TUM RGB-D sequence that name its images (lines ``timestamp filename``, ``#`` comments).
TUM_LISTS = ("rgb.txt", "depth.txt")
#: PEP 706's extraction filter where this Python has it (3.12, 3.11.4, 3.10.12): besides the member checks
#: of :func:`extract_sequence`, it refuses any member that would land outside the destination.
TAR_FILTER: dict[str, str] = {"filter": "data"} if hasattr(tarfile, "data_filter") else {}


class FetchError(DataError):
    """A dataset could not be fetched; the message is one line and says what to do."""


def extract_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, target: Path) -> None:
    """Write one archive member to ``target``; the zip module checks its CRC-32 at the end of the read."""
    target.parent.mkdir(parents=True, exist_ok=True)
    with zf.open(info) as src, open(target, "wb") as dst:
        shutil.copyfileobj(src, dst, CHUNK)


def _scene_prefix(zf: zipfile.ZipFile, archive: Path, scene: str) -> str:
    """The member-name prefix of ``scene/`` inside the archive (``nerf_synthetic/lego/``)."""
    for name in zf.namelist():
        if name.endswith(f"{scene}/transforms_train.json") and not name.startswith("__MACOSX/"):
            return name[:-len("transforms_train.json")]
    raise FetchError(f"{archive.name}: no {scene}/transforms_train.json in the archive (not the NeRF-synthetic "
                     f"archive?)")


def extract_scene(archive: Path, scene: str, out: Path, *, progress: bool = True) -> None:
    """Extract the folder ``scene/`` of a zip archive (wherever it sits in it) into ``out``; a failed write
    raises its ``OSError``."""
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError) as exc:
        raise FetchError(f"{archive}: not a readable zip archive ({exc})") from None
    with zf:
        prefix = _scene_prefix(zf, archive, scene)
        members = [i for i in zf.infolist() if i.filename.startswith(prefix) and not i.is_dir()]
        for info in tqdm(members, desc=f"extract {scene}", unit="file", disable=None if progress else True,
                         leave=False):
            rel = PurePosixPath(info.filename[len(prefix):])
            if rel.is_absolute() or ".." in rel.parts:
                raise FetchError(f"{archive.name}: unsafe member name {info.filename!r}")
            try:
                extract_member(zf, info, out.joinpath(*rel.parts))
            except zipfile.BadZipFile as exc:
                raise FetchError(f"{archive.name}: corrupt archive ({exc})") from None


def scene_frames(folder: Path, what: str) -> list[Path]:
    """The frame images named in ``folder``'s ``transforms_{train,val,test}.json``, relative to ``folder``."""
    rels = []
    for split in SPLITS:
        try:
            frames = json.loads((folder / f"transforms_{split}.json").read_text())["frames"]
            names = [Path(str(frame["file_path"])) for frame in frames]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise FetchError(f"{what}: no readable transforms_{split}.json with frames "
                             f"({type(exc).__name__})") from None
        rels += [rel if rel.suffix else rel.with_suffix(".png") for rel in names]
    return rels


def check_scene(folder: Path, what: str) -> None:
    """Every split's transforms JSON and every frame image it names exist in ``folder``."""
    for rel in scene_frames(folder, what):
        if not (folder / rel).is_file():
            raise FetchError(f"{what}: the transforms name {rel}, which is missing")


def extract_sequence(archive: Path, scene: str, out: Path, *, progress: bool = True) -> None:
    """Extract the top folder ``scene/`` of a gzip-compressed tar archive into ``out``; a failed write raises its
    ``OSError``.

    Any member with an absolute name or ``..`` is refused, as is a link or device file in ``scene/``; members
    outside ``scene/`` are skipped. The archive is read once, to its end, so that gzip checks the CRC-32 of
    every byte.
    """
    bad = (tarfile.TarError, gzip.BadGzipFile, EOFError, zlib.error)
    found = False
    with contextlib.ExitStack() as stack:
        try:
            gz = stack.enter_context(gzip.open(archive))
            tf = stack.enter_context(tarfile.open(fileobj=gz, mode="r|"))
        except (OSError, *bad) as exc:
            raise FetchError(f"{archive}: not a readable .tgz (gzip-compressed tar) archive ({exc})") from None
        try:
            for member in tqdm(tf, desc=f"extract {scene}", unit="file", disable=None if progress else True,
                               leave=False):
                rel = PurePosixPath(member.name)
                if rel.is_absolute() or ".." in rel.parts:
                    raise FetchError(f"{archive.name}: unsafe member name {member.name!r}")
                if rel.parts[:1] != (scene,):
                    continue
                found = True
                if not (member.isfile() or member.isdir()):
                    raise FetchError(f"{archive.name}: {member.name!r} is neither a file nor a folder")
                if len(rel.parts) > 1:
                    item = copy.copy(member)
                    item.name = str(PurePosixPath(*rel.parts[1:]))
                    tf.extract(item, out, set_attrs=False, **TAR_FILTER)
            while gz.read(CHUNK):  # the rest, up to gzip's CRC-32 and length, checked at the end
                pass
        except bad as exc:
            raise FetchError(f"{archive.name}: corrupt archive ({type(exc).__name__}: {exc})") from None
    if not found:
        raise FetchError(f"{archive.name}: no {scene}/ folder in the archive (not the TUM RGB-D archive of "
                         f"this sequence?)")


def check_sequence(folder: Path, what: str) -> None:
    """``groundtruth.txt``, ``rgb.txt`` and ``depth.txt`` exist in ``folder`` and so does every image these two
    name (lines ``timestamp filename``, ``#`` comments)."""
    for listing in TUM_LISTS:
        try:
            lines = (folder / listing).read_text(encoding="utf-8").splitlines()
        except (OSError, ValueError) as exc:
            raise FetchError(f"{what}: no readable {listing} ({type(exc).__name__})") from None
        frames = 0
        for number, line in enumerate(lines, 1):
            fields = line.split()
            if not fields or fields[0].startswith("#"):
                continue
            rel = PurePosixPath(fields[-1])
            if len(fields) != 2 or rel.is_absolute() or ".." in rel.parts:
                raise FetchError(f"{what}: {listing} line {number} is not 'timestamp filename' of a file in the "
                                 f"sequence: {line.strip()!r}")
            if not folder.joinpath(*rel.parts).is_file():
                raise FetchError(f"{what}: {listing} names {rel}, which is missing")
            frames += 1
        if not frames:
            raise FetchError(f"{what}: {listing} names no images")
    if not (folder / "groundtruth.txt").is_file():
        raise FetchError(f"{what}: no groundtruth.txt")

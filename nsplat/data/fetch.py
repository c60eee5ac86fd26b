"""Download the public datasets into the data root (``nsplat data fetch lego|nerf_synthetic|dss|tum_*``;
docs/data.md).

Each dataset is built in a sibling folder ``<dest>.part`` and renamed into place when complete, so the
destination either holds the whole dataset or does not exist. Downloads go to ``<name>.part`` inside that
folder and continue with an HTTP ``Range`` request when the command runs again; they are kept only when a
download was cut off (or the process interrupted). Any other failure (checksum mismatch, bad archive, full
disk) removes the partial folder and reports one line (:class:`FetchError`).

The eight NeRF-synthetic scenes (:data:`~nsplat.data.nerf_scenes.NERF_SCENES`, each a dataset of its own, all
of them together the group ``nerf_synthetic``) come from one archive: :func:`fetch_together` downloads it
once for every scene of one command, extracts each scene into its own folder and renames it into place, and
a partial download any earlier command of one of these scenes left behind is resumed, whichever scene it was for.

Checksums: the DSS point clouds are pinned to the sha256 of the published files. The NeRF authors publish
no checksum for ``nerf_synthetic.zip``: it is verified by the zip's own CRC-32 of every extracted file and
by the scene's structure (every frame named in the transforms is present); its sha256 is printed and
recorded in ``<dest>/SOURCE.json``, and ``--sha256`` requires a known value. The same holds for the TUM RGB-D
sequences (``.tgz``), which are verified by gzip's CRC-32 of the whole archive and by the sequence's
structure (every image named in ``rgb.txt`` and ``depth.txt`` is present, and ``groundtruth.txt``).
"""
from __future__ import annotations

import dataclasses
import errno
import hashlib
import http.client
import json
import os
import shutil
import urllib.error
import urllib.request
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Literal

from tqdm import tqdm

from nsplat.data.archives import CHUNK, FetchError, check_scene, check_sequence, extract_scene, extract_sequence
from nsplat.data.nerf_scenes import NERF_SCENES

#: Seconds a connection may stay silent before the download counts as interrupted.
TIMEOUT_S = 60.0
#: The DSS repository commit whose ``example_data/pointclouds`` holds the shape-reconstruction clouds.
DSS_COMMIT = "341063495ad57b4eff34bc9fee21b1fa7cb3f208"
DSS_RAW = f"https://raw.githubusercontent.com/yifita/DSS/{DSS_COMMIT}/example_data/pointclouds"
#: ``nerf_synthetic.zip`` in the NeRF authors' data folder (linked as "Data" from github.com/bmild/nerf).
NERF_FOLDER = "https://drive.google.com/drive/folders/128yBriW1IG_3NJ5Rp7APSTZsJqdJdfc1"
NERF_ZIP = ("https://drive.usercontent.google.com/download?id=18JxhpWD-4ZmuFKLzKlAw-w5PpzZxXOcG"
            "&export=download&confirm=t")
#: The TUM RGB-D benchmark (Sturm et al., IROS 2012): its archives, and the page that links them.
TUM_BASE = "https://cvg.cit.tum.de/rgbd/dataset"
TUM_DOWNLOAD = "https://cvg.cit.tum.de/data/datasets/rgbd-dataset/download"
#: The TUM RGB-D sequences offered, by camera (``freiburg1``-``3``); dataset ``tum_fr<camera>_<sequence>``.
TUM_SEQUENCES: dict[int, tuple[str, ...]] = {
    1: ("xyz", "rpy", "360", "floor", "desk", "desk2", "room"),
    2: ("xyz", "rpy", "desk"),
    3: ("long_office_household",),
}


class DownloadInterrupted(FetchError):
    """A download stopped before its end; the partial file is kept and the next run resumes it."""


class SourceError(FetchError):
    """The source answered with an error or with something other than the file (an HTML page)."""


@dataclasses.dataclass(frozen=True)
class Remote:
    """One published file: its name, where it is published and its sha256 (``None``: none published)."""

    name: str
    url: str
    sha256: str | None


@dataclasses.dataclass(frozen=True)
class Dataset:
    """A dataset: its folder under the data root, its files, and for an archive the scene folder to extract.

    Attributes:
        dest: destination relative to the data root. files: the published files.
        scene: the folder extracted from the (single) archive; ``None``: the files are the dataset.
        manual: what to do when the source does not deliver (where to download the files by hand).
        layout: how the archive is unpacked and checked (:data:`LAYOUTS`); unused when ``scene`` is ``None``.
    """

    dest: str
    files: tuple[Remote, ...]
    scene: str | None
    manual: str
    layout: Literal["nerf", "tum"] = "nerf"


def tum_dataset(camera: int, sequence: str) -> Dataset:
    """TUM RGB-D sequence ``rgbd_dataset_freiburg<camera>_<sequence>``: its archive, unpacked into
    ``rgbd/<the archive's folder>``."""
    folder = f"rgbd_dataset_freiburg{camera}_{sequence}"
    archive = Remote(f"{folder}.tgz", f"{TUM_BASE}/freiburg{camera}/{folder}.tgz", None)
    return Dataset(f"rgbd/{folder}", (archive,), folder,
                   f"download {archive.name} by hand from {TUM_DOWNLOAD} and pass --archive FILE", "tum")


#: The NeRF authors' archive of the eight NeRF-synthetic scenes (no checksum published).
NERF_ARCHIVE = Remote("nerf_synthetic.zip", NERF_ZIP, None)

DATASETS: dict[str, Dataset] = {
    **{scene: Dataset(f"nerf_synthetic/{scene}", (NERF_ARCHIVE,), scene,
                      f"download nerf_synthetic.zip by hand from {NERF_FOLDER} and pass --archive FILE")
       for scene in NERF_SCENES},
    "dss": Dataset("dss_pointclouds", tuple(Remote(name, f"{DSS_RAW}/{name}", sha) for name, sha in (
        ("bunny-8000.ply", "bec459fd076e3ee8871d1d23346222081d9689a8a7a71133e4f4855b5c7283a0"),
        ("teapot_normal_dense.ply", "9dcde8c6f40bf234927c2335c7be0c331e1101aab8332f6b76acbeaf6855c8f1"),
        ("yoga1_out.ply", "99721808e5560192200693efe2ddc1324f0d00e8b75b9824f19dd07f01c29202"),
        ("yoga6_out.ply", "d14e8cb48c1ec795b19452a5bb603d4884e753646f8219b0441af24f7b378ec5"),
    )), None, f"the files are published at https://github.com/yifita/DSS/tree/{DSS_COMMIT}/example_data/pointclouds"),
    **{f"tum_fr{camera}_{sequence}": tum_dataset(camera, sequence)
       for camera, sequences in TUM_SEQUENCES.items() for sequence in sequences},
}
#: Names that stand for several datasets of one archive: ``nerf_synthetic`` is its eight scenes.
GROUPS: dict[str, tuple[str, ...]] = {"nerf_synthetic": NERF_SCENES}


def expand(names: Iterable[str]) -> list[str]:
    """The datasets ``names`` stand for (a :data:`GROUPS` name for its members), each once, in order."""
    return list(dict.fromkeys(member for name in names for member in GROUPS.get(name, (name,))))


def write_error(exc: OSError, folder: Path) -> FetchError:
    """A one-line :class:`FetchError` for an ``OSError`` raised while writing into ``folder``."""
    if exc.errno == errno.ENOSPC:
        return FetchError(f"disk full: no space left in {folder}; free some space (or choose another folder with "
                          f"--root / $NSPLAT_DATA) and run the command again")
    return FetchError(f"cannot write in {folder}: {exc.strerror or exc} (choose a writable folder with --root or "
                      f"$NSPLAT_DATA)")


def sha256_of(path: Path) -> str:
    """Hex sha256 of a file."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def _open(url: str, offset: int) -> http.client.HTTPResponse:
    """GET ``url`` from byte ``offset`` (a ``Range`` request when ``offset > 0``)."""
    headers = {"User-Agent": "nsplat-data-fetch"}
    if offset:
        headers["Range"] = f"bytes={offset}-"
    try:
        return urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=TIMEOUT_S)
    except urllib.error.HTTPError as exc:
        if exc.code == 416 and offset:
            raise  # the caller restarts from byte 0
        raise SourceError(f"{url}: HTTP {exc.code} {exc.reason}") from None
    except (urllib.error.URLError, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        raise DownloadInterrupted(f"cannot reach {url} ({reason}); run the same command again to retry") from None


def download(url: str, part: Path, *, progress: bool = True) -> None:
    """Fetch ``url`` into ``part``, continuing from the bytes already there (HTTP ``Range``).

    Raises :class:`DownloadInterrupted` when the body ends early or the connection breaks (``part`` keeps
    what arrived), :class:`SourceError` for HTTP errors or an HTML page where a file was expected, and the
    ``OSError`` of a failed write.
    """
    offset = part.stat().st_size if part.exists() else 0
    try:
        resp = _open(url, offset)
    except urllib.error.HTTPError:  # 416: the part is not a prefix of the file; start again
        part.unlink()
        offset, resp = 0, _open(url, 0)
    with resp:
        if resp.headers.get_content_type() == "text/html" and not url.endswith((".html", ".htm")):
            raise SourceError(f"{url} sent an HTML page instead of {part.name[:-len('.part')]} (a download quota or "
                             f"sign-in page?)")
        if resp.status != 206:
            offset = 0  # the server ignored the Range header: the body is the whole file
        elif not resp.headers.get("Content-Range", "").startswith(f"bytes {offset}-"):
            raise SourceError(f"{url}: the server answered the resume request with the wrong range "
                             f"({resp.headers.get('Content-Range')!r}); delete {part} and run again")
        length = resp.headers.get("Content-Length")
        total = offset + int(length) if length and length.isdigit() else None
        broken = ""
        with open(part, "ab" if offset else "wb") as out, tqdm(
                total=total, initial=offset, unit="B", unit_scale=True, unit_divisor=1024,
                desc=part.name[:-len(".part")], disable=None if progress else True, leave=False) as bar:
            while True:
                try:
                    chunk = resp.read1(CHUNK)  # what has arrived: nothing is lost when the link breaks
                except (http.client.HTTPException, OSError) as exc:  # the connection, not the disk
                    broken = f"interrupted ({type(exc).__name__})"
                    break
                if not chunk:
                    break
                out.write(chunk)
                bar.update(len(chunk))
    got = part.stat().st_size
    if broken or (total is not None and got < total):
        raise DownloadInterrupted(f"download of {url} {broken or 'cut off'} after {got} of {total or 'unknown'} "
                                  f"bytes; run the same command again to resume (partial file {part})")


def obtain(remote: Remote, stage: Path, *, mirror: str | None, sha256: str | None,
           progress: bool) -> tuple[Path, str]:
    """Download ``remote`` into ``stage`` (resuming a partial ``.part``) and check its sha256.

    Returns the verified file and its sha256. ``sha256`` (when given) overrides the manifest's value; a
    mismatch removes the file and raises :class:`FetchError` naming the file and both hashes.
    """
    final = stage / remote.name
    url = f"{mirror.rstrip('/')}/{remote.name}" if mirror else remote.url
    if not final.is_file():  # else: downloaded by an earlier, interrupted run of this command
        part = stage / f"{remote.name}.part"
        download(url, part, progress=progress)
        os.replace(part, final)
    got = sha256_of(final)
    expected = (sha256 or remote.sha256 or "").lower() or None
    if expected is not None and got != expected:
        final.unlink()
        raise FetchError(f"checksum mismatch for {remote.name} from {url}: expected sha256 {expected}, got {got}; "
                         f"the file was removed")
    return final, got


@dataclasses.dataclass(frozen=True)
class Layout:
    """How a dataset's archive is unpacked (``extract(archive, scene, out, progress=...)``) and its folder
    checked (``check(folder, what)``), and what that verifies of an archive without a published checksum."""

    extract: Callable[..., None]
    check: Callable[[Path, str], None]
    verified: str


#: The layouts of :attr:`Dataset.layout`.
LAYOUTS: dict[str, Layout] = {
    "nerf": Layout(extract_scene, check_scene, "its zip CRC-32s and the scene's files"),
    "tum": Layout(extract_sequence, check_sequence, "its gzip CRC-32 and the sequence's files"),
}


def present(ds: Dataset, dest: Path) -> bool:
    """Whether ``dest`` already holds the dataset; a folder that holds something else is an error."""
    if not dest.exists():
        return False
    if ds.scene is not None:
        LAYOUTS[ds.layout].check(dest, str(dest))
        return True
    for remote in ds.files:
        path = dest / remote.name
        if not path.is_file() or (remote.sha256 and sha256_of(path) != remote.sha256):
            raise FetchError(f"{dest} exists but {remote.name} is missing or differs from the published file; "
                             f"move the folder away and run the command again")
    return True


def _made_dirs(path: Path) -> list[Path]:
    """Create ``path`` and its missing parents; returns the folders created, deepest first."""
    missing = [p for p in (path, *path.parents) if not p.exists()]
    path.mkdir(parents=True, exist_ok=True)
    return missing


@dataclasses.dataclass
class Fetched:
    """What :func:`fetch` did: the dataset's folder, whether it was already there, and per downloaded file
    ``{file, url, sha256, bytes, checksum}`` (``checksum``: ``verified`` or ``none published``)."""

    dest: Path
    already: bool
    files: list[dict[str, object]]


def _obtain_all(ds: Dataset, stage: Path, *, mirror: str | None, sha256: str | None, archive: Path | None,
                progress: bool) -> tuple[list[dict[str, object]], list[Path]]:
    """Download (or take from ``archive``) and verify the files of ``ds`` in ``stage``; returns the per-file
    records and the files."""
    records, paths = [], []
    for remote in ds.files:
        if archive is not None:
            path, digest = archive, sha256_of(archive)
            if sha256 and digest != sha256.lower():
                raise FetchError(f"checksum mismatch for {archive}: expected sha256 {sha256.lower()}, got {digest}")
        else:
            path, digest = obtain(remote, stage, mirror=mirror, sha256=sha256, progress=progress)
        records.append({"file": remote.name, "url": str(archive or remote.url), "sha256": digest,
                        "bytes": path.stat().st_size,
                        "checksum": "verified" if sha256 or remote.sha256 else "none published"})
        paths.append(path)
    return records, paths


def _lay_out(name: str, ds: Dataset, records: list[dict[str, object]], paths: list[Path], tree: Path, *,
             progress: bool) -> None:
    """Lay out dataset ``name`` in ``tree`` from its verified files (moved, or its scene extracted and checked)."""
    tree.mkdir()
    if ds.scene is None:
        for remote, path in zip(ds.files, paths):
            os.replace(path, tree / remote.name)
    else:
        layout = LAYOUTS[ds.layout]
        layout.extract(paths[0], ds.scene, tree, progress=progress)
        layout.check(tree, f"{ds.files[0].name}: {ds.scene}/")
    (tree / "SOURCE.json").write_text(json.dumps({"dataset": name, "files": records}, indent=1) + "\n")


def fetch(name: str, root: Path, *, mirror: str | None = None, sha256: str | None = None,
          archive: Path | None = None, progress: bool = True) -> Fetched:
    """Fetch dataset ``name`` (:data:`DATASETS`) into ``root``, atomically; see the module docstring.

    ``mirror`` replaces the published base URLs (``<mirror>/<file name>``); ``sha256`` requires that hash of
    the archive; ``archive`` uses a local copy of it instead of downloading.
    """
    return fetch_together([name], root, mirror=mirror, sha256=sha256, archive=archive, progress=progress)[0]


def _stage(names: Sequence[str], root: Path) -> Path:
    """Where the shared files of datasets ``names`` (all missing) are downloaded: the ``<dest>.part`` folder
    an earlier command left for any dataset of the same files (a partial download to resume), else the
    first dataset's."""
    files = DATASETS[names[0]].files
    siblings = dict.fromkeys([*names, *(n for n, d in DATASETS.items() if d.files == files and d.scene)])
    stages = [(root / DATASETS[n].dest).with_name(Path(DATASETS[n].dest).name + ".part") for n in siblings]
    return next((s for s in stages if s.is_dir()), stages[0])


def fetch_together(names: Sequence[str], root: Path, *, mirror: str | None = None, sha256: str | None = None,
                   archive: Path | None = None, progress: bool = True,
                   report: Callable[[str, Fetched], None] | None = None) -> list[Fetched]:
    """Fetch datasets ``names`` that share their published files (several NeRF-synthetic scenes: one
    ``nerf_synthetic.zip``) into ``root`` with one download; returns what :func:`fetch` does, per name.

    Each dataset is renamed into place as soon as it is complete (and passed to ``report``), so a failure
    leaves the datasets before it whole and the others absent. Arguments as :func:`fetch`.
    """
    dss = [DATASETS[name] for name in names]
    if len({ds.files for ds in dss}) != 1 or (len(dss) > 1 and any(ds.scene is None for ds in dss)):
        raise ValueError(f"{', '.join(names)}: fetched together only when they are scenes of one archive")
    if (sha256 or archive) and len(dss[0].files) != 1:
        raise ValueError(f"{names[0]}: sha256 and archive apply to a dataset of one archive")
    if archive is not None and not archive.is_file():
        raise FetchError(f"--archive {archive}: no such file")
    done: dict[str, Fetched] = {}
    for name, ds in zip(names, dss):
        if present(ds, root / ds.dest):
            done[name] = Fetched(root / ds.dest, True, [])
            if report is not None:
                report(name, done[name])
    missing = [name for name in names if name not in done]
    if not missing:
        return [done[name] for name in names]
    stage = _stage(missing, root)
    try:
        created = _made_dirs(stage)
    except OSError as exc:
        raise write_error(exc, root) from None
    tree = stage / "tree"
    shutil.rmtree(tree, ignore_errors=True)  # left by a killed run
    resumable = False
    try:
        records, paths = _obtain_all(dss[0], stage, mirror=mirror, sha256=sha256, archive=archive,
                                     progress=progress)
        for name in missing:
            ds = DATASETS[name]
            _lay_out(name, ds, records, paths, tree, progress=progress)
            os.replace(tree, root / ds.dest)
            done[name] = Fetched(root / ds.dest, False, records)
            if report is not None:
                report(name, done[name])
    except OSError as exc:
        raise write_error(exc, root) from None
    except SourceError as exc:
        raise SourceError(f"{exc}; {dss[0].manual}") from None
    except (DownloadInterrupted, KeyboardInterrupt):
        resumable = True
        raise
    finally:
        if not resumable or not any(stage.iterdir()):
            shutil.rmtree(stage, ignore_errors=True)
            for folder in created[1:]:  # the parents this call created, when they stayed empty
                if folder.is_dir() and not any(folder.iterdir()):
                    folder.rmdir()
    return [done[name] for name in names]

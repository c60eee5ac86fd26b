"""``nsplat data fetch|prepare`` against a local HTTP server on 127.0.0.1: a full fetch that the loaders read,
resume after a cut-off download, checksum mismatch, full disk, the command line's one-line errors, all eight
NeRF-synthetic scenes from one zip the test writes (one download, by group or by name, the configs' ``data.scene``),
and a TUM RGB-D sequence (.tgz) with the archives it must refuse."""
from __future__ import annotations

import dataclasses
import errno
import hashlib
import http.server
import io
import json
import os
import shutil
import subprocess
import sys
import tarfile
import threading
import zipfile
from pathlib import Path
from typing import Iterator

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from nsplat import cli
from nsplat.config import ConfigError, load_config, read_yaml
from nsplat.data import archives as archives_mod
from nsplat.data import fetch as fetch_mod
from nsplat.data import prepare as prepare_mod
from nsplat.data.nerf_synthetic import SPLITS, load_split
from nsplat.data.paths import data_root, resolve
from nsplat.data.pointclouds import load_dss_shape
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.data import load_views

REPO = Path(__file__).resolve().parents[1]
SIDE = 8  # fixture image side; prepared at 4


def _png(seed: int) -> bytes:
    """An 8×8 RGBA PNG with opaque, half-transparent and transparent pixels."""
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (SIDE, SIDE, 4), dtype=np.uint8)
    img[:2, :, 3] = 0
    img[2:4, :, 3] = 128
    img[4:, :, 3] = 255
    return iio.imwrite("<bytes>", img, extension=".png")


def _nerf_zip(scenes: tuple[str, ...] = ("lego",)) -> bytes:
    """A NeRF-synthetic-style ``nerf_synthetic.zip``: ``nerf_synthetic/<scene>`` with 2 frames per split for each of
    ``scenes`` (each scene's own pixels), and macOS metadata that must not be extracted."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for k, scene in enumerate(scenes):
            for s, split in enumerate(SPLITS):
                frames = []
                for i in range(2):
                    c2w = [[1.0, 0.0, 0.0, 0.1 * i], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0], [0.0, 0.0, 0.0, 1.0]]
                    frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0125, "transform_matrix": c2w})
                    zf.writestr(f"nerf_synthetic/{scene}/{split}/r_{i}.png", _png(100 * k + 10 * s + i))
                zf.writestr(f"nerf_synthetic/{scene}/transforms_{split}.json",
                            json.dumps({"camera_angle_x": 0.6911, "frames": frames}))
            zf.writestr(f"__MACOSX/nerf_synthetic/{scene}/._transforms_train.json", "junk")
    return buf.getvalue()


def _lego_zip() -> bytes:
    """``nerf_synthetic.zip`` with lego only, and a broken ship (an empty transforms file) that must not be read."""
    data = io.BytesIO(_nerf_zip())
    with zipfile.ZipFile(data, "a") as zf:
        zf.writestr("nerf_synthetic/ship/transforms_train.json", "{}")
    return data.getvalue()


def _ply(n: int) -> bytes:
    """A binary PLY with ``n`` oriented vertices."""
    rng = np.random.default_rng(n)
    v = np.zeros(n, dtype=[(k, "f4") for k in ("x", "y", "z", "nx", "ny", "nz")])
    for k in ("x", "y", "z"):
        v[k] = rng.normal(size=n)
    v["nz"] = 1.0
    buf = io.BytesIO()
    PlyData([PlyElement.describe(v, "vertex")]).write(buf)
    return buf.getvalue()


TUM = "rgbd_dataset_freiburg1_rpy"  # the folder in tum_fr1_rpy's archive


def _tum_files(folder: str = TUM) -> dict[str, bytes | None]:
    """The members of a TUM RGB-D sequence archive (``None``: a folder): three 8×6 colour and three 16-bit depth
    frames at their own timestamps, the lists naming them, ground truth and accelerometer data."""
    rng = np.random.default_rng(5)
    files: dict[str, bytes | None] = {"": None, "rgb": None, "depth": None}
    lists = {"rgb": ["# color images", "# timestamp filename"], "depth": ["# depth maps", "# timestamp filename"]}
    for i in range(3):
        for kind, img in (("rgb", rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)),
                          ("depth", rng.integers(0, 1 << 16, (6, 8), dtype=np.uint16))):
            stamp = f"{1305031790.6 + i / 30 + (0.01 if kind == 'depth' else 0.0):.6f}"
            files[f"{kind}/{stamp}.png"] = iio.imwrite("<bytes>", img, extension=".png")
            lists[kind].append(f"{stamp} {kind}/{stamp}.png")
    for kind, lines in lists.items():
        files[f"{kind}.txt"] = "\n".join([*lines, ""]).encode()
    files["groundtruth.txt"] = b"# timestamp tx ty tz qx qy qz qw\n1305031790.6 1.2 -0.3 1.5 0.6 0.6 -0.3 -0.3\n"
    files["accelerometer.txt"] = b"# timestamp ax ay az\n1305031790.6 0.1 -9.7 -0.6\n"
    return {f"{folder}/{name}".rstrip("/"): data for name, data in files.items()}


def _tgz(members: dict[str, bytes | None], symlinks: dict[str, str] | None = None) -> bytes:
    """A gzip-compressed tar of ``members`` (name: bytes, or ``None`` for a folder) and ``symlinks`` (name: target)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            if data is None:
                info.type, info.mode = tarfile.DIRTYPE, 0o755
            else:
                info.size = len(data)
            tf.addfile(info, None if data is None else io.BytesIO(data))
        for name, target in (symlinks or {}).items():
            info = tarfile.TarInfo(name)
            info.type, info.linkname = tarfile.SYMTYPE, target
            tf.addfile(info)
    return buf.getvalue()


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


class Server:
    """A threaded HTTP server on 127.0.0.1 serving ``files`` with ``Range`` support. ``cut[name] = n`` makes
    the next GET of ``name`` announce the full length but send ``n`` bytes and close; ``requests`` records
    ``(name, Range header)``. Stops on exit, and by itself after a minute at most."""

    def __init__(self, files: dict[str, bytes]) -> None:
        self.files, self.cut, self.requests = files, {}, []
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 - http.server's naming
                name = self.path.lstrip("/")
                server.requests.append((name, self.headers.get("Range")))
                if name not in server.files:
                    self.send_error(404)
                    return
                data = server.files[name]
                start = int(self.headers["Range"][len("bytes="):].rstrip("-")) if self.headers.get("Range") else 0
                self.send_response(206 if start else 200)
                self.send_header("Content-Type", "application/octet-stream")
                self.send_header("Content-Length", str(len(data) - start))
                if start:
                    self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
                self.end_headers()
                self.wfile.write(data[start:start + server.cut.pop(name, len(data))])

            def log_message(self, *args: object) -> None:
                """Quiet."""

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        self.watchdog = threading.Timer(60.0, self.httpd.shutdown)

    def __enter__(self) -> Server:
        self.thread.start()
        self.watchdog.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.watchdog.cancel()
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(timeout=5)


DSS_FILES = {name: _ply(20 + i) for i, name in enumerate(
    ("bunny-8000.ply", "teapot_normal_dense.ply", "yoga1_out.ply", "yoga6_out.ply"))}


@pytest.fixture
def server(monkeypatch: pytest.MonkeyPatch) -> Iterator[Server]:
    """The fixture archive and point clouds on a local server; the DSS manifest pinned to the fixtures' hashes."""
    dss = fetch_mod.DATASETS["dss"]
    monkeypatch.setitem(fetch_mod.DATASETS, "dss", dataclasses.replace(dss, files=tuple(
        dataclasses.replace(r, sha256=_sha(DSS_FILES[r.name])) for r in dss.files)))
    with Server({"nerf_synthetic.zip": _lego_zip(), **DSS_FILES}) as srv:
        yield srv


def _run(capsys: pytest.CaptureFixture, *argv: str) -> tuple[int, str, list[str]]:
    """``nsplat data ...`` in-process: exit code, stdout, stderr lines."""
    code = cli.main(["data", *argv])
    out, err = capsys.readouterr()
    return code, out, err.splitlines()


def _files(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*")) if root.exists() else []


def test_fetch_lego_and_prepare_give_a_loadable_scene(server, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("NSPLAT_DATA", str(tmp_path / "data"))
    code, out, err = _run(capsys, "fetch", "lego", "--resolution", "4", "--mirror", server.url)
    assert code == 0 and err == []
    lego, lego4 = data_root() / "nerf_synthetic" / "lego", data_root() / "nerf_synthetic" / "lego_4"
    assert f"lego: fetched into {lego}" in out and f"lego_4: written to {lego4}" in out
    assert f"sha256 {_sha(server.files['nerf_synthetic.zip'])}" in out and "no checksum is published" in out
    assert "note:" not in out  # the data went to $NSPLAT_DATA
    assert sorted(p.name for p in (tmp_path / "data" / "nerf_synthetic").iterdir()) == ["lego", "lego_4"]
    assert sorted(p.name for p in lego.iterdir()) == ["SOURCE.json", "test", "train", "transforms_test.json",
                                                      "transforms_train.json", "transforms_val.json", "val"]
    assert json.loads((lego / "SOURCE.json").read_text())["files"][0]["checksum"] == "none published"
    assert resolve("$NSPLAT_DATA/nerf_synthetic/lego_4") == lego4
    for split in SPLITS:
        small = load_split(lego4, split)
        assert small.images.shape == (2, 4, 4, 3)
        # premultiplied area averaging: compositing the 4² copy equals area-averaging the composited 8² original
        ref = load_split(lego, split, resolution=4)
        assert torch.allclose(small.images, ref.images, atol=2.5 / 255) and torch.allclose(small.Ks, ref.Ks)
        assert torch.allclose(small.masks, ref.masks, atol=1 / 255)
    before = len(server.requests)
    code, out, _ = _run(capsys, "fetch", "lego", "--resolution", "4", "--mirror", server.url)
    assert code == 0 and f"lego_4: already in {lego4}" in out and len(server.requests) == before


def test_cut_off_download_resumes_with_a_range_request(server, tmp_path, capsys):
    root, size = tmp_path / "data", len(server.files["nerf_synthetic.zip"])
    server.cut["nerf_synthetic.zip"] = size // 2
    code, _, err = _run(capsys, "fetch", "lego", "--root", str(root), "--mirror", server.url)
    assert code == 2 and len(err) == 1 and err[0].startswith("error: download of ")
    assert f"cut off after {size // 2} of {size} bytes" in err[0] and "resume" in err[0]
    assert _files(root) == ["nerf_synthetic", "nerf_synthetic/lego.part",
                            "nerf_synthetic/lego.part/nerf_synthetic.zip.part"]
    code, out, err = _run(capsys, "fetch", "lego", "--root", str(root), "--mirror", server.url)
    assert code == 0 and err == [] and f"note: set NSPLAT_DATA={root}" in out
    assert server.requests[-1] == ("nerf_synthetic.zip", f"bytes={size // 2}-")
    assert not (root / "nerf_synthetic" / "lego.part").exists()
    assert load_split(root / "nerf_synthetic" / "lego", "train").images.shape == (2, SIDE, SIDE, 3)


def test_checksum_mismatch_is_one_line_and_leaves_nothing(server, tmp_path, capsys):
    root = tmp_path / "data"
    good = server.files["yoga1_out.ply"]
    server.files["yoga1_out.ply"] = good[:-4] + b"\0\0\0\0"
    code, _, err = _run(capsys, "fetch", "dss", "--root", str(root), "--mirror", server.url)
    assert code == 2 and len(err) == 1
    assert "checksum mismatch for yoga1_out.ply" in err[0] and _sha(good) in err[0]
    assert _sha(server.files["yoga1_out.ply"]) in err[0]
    assert _files(root) == []
    wrong = "0" * 64
    code, _, err = _run(capsys, "fetch", "lego", "--root", str(root), "--mirror", server.url, "--sha256", wrong)
    assert code == 2 and len(err) == 1 and f"expected sha256 {wrong}" in err[0] and _files(root) == []


def test_full_disk_is_one_line_and_leaves_nothing_half_extracted(server, tmp_path, monkeypatch, capsys):
    root = tmp_path / "data"
    written = []

    def fill_disk(zf: zipfile.ZipFile, info: zipfile.ZipInfo, target: Path) -> None:
        if len(written) == 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(target))
        extract(zf, info, target)
        written.append(target)

    extract = archives_mod.extract_member
    monkeypatch.setattr(archives_mod, "extract_member", fill_disk)
    code, _, err = _run(capsys, "fetch", "lego", "--root", str(root), "--mirror", server.url)
    assert code == 2 and err == [f"error: disk full: no space left in {root}; free some space (or choose another "
                                 f"folder with --root / $NSPLAT_DATA) and run the command again"]
    assert len(written) == 3 and _files(root) == []

    monkeypatch.setattr(archives_mod, "extract_member", extract)
    calls = []

    def fill_disk_later(src: Path, dst: Path, width: int) -> None:
        calls.append(dst)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dst))
        downscale(src, dst, width)

    downscale = prepare_mod._downscale_file
    monkeypatch.setattr(prepare_mod, "_downscale_file", fill_disk_later)
    code, _, err = _run(capsys, "fetch", "lego", "--root", str(root), "--mirror", server.url, "--resolution", "4")
    assert code == 2 and len(err) == 1 and err[0].startswith("error: disk full")
    assert sorted(p.name for p in (root / "nerf_synthetic").iterdir()) == ["lego"]  # fetched, not prepared


def test_dss_fetch_prints_the_destination_and_loads(server, tmp_path, capsys):
    root = tmp_path / "data"
    code, out, err = _run(capsys, "fetch", "dss", "--root", str(root), "--mirror", server.url, "--quiet")
    dest = root / "dss_pointclouds"
    assert code == 0 and err == [] and f"dss: fetched into {dest}" in out and "no checksum" not in out
    assert sorted(p.name for p in dest.iterdir()) == sorted([*DSS_FILES, "SOURCE.json"])
    assert load_dss_shape("teapot", root).points.shape == (21, 3)
    code, out, _ = _run(capsys, "fetch", "dss", "--root", str(root), "--mirror", server.url)
    assert code == 0 and f"dss: already in {dest}" in out


@pytest.mark.parametrize("argv, message", [
    (["fetch", "dss", "--resolution", "400"], "usage error: --resolution applies to the NeRF-synthetic scenes (chair,"),
    (["fetch", "lego", "--sha256", "abc"], "usage error: --sha256: expected 64 hexadecimal digits"),
    (["fetch", "chairs"], "usage error: nsplat data fetch: argument DATASET: invalid choice: 'chairs'"),
    (["prepare", "lego"], "usage error: nsplat data prepare: the following arguments are required: --resolution"),
    (["prepare", "lego", "--resolution", "4"], "error: no scene at"),
    (["prepare", "ship", "--resolution", "4"], "error: no scene at"),
    (["prepare", "nerf_synthetic", "--resolution", "4"], "usage error: nsplat data prepare: argument SCENE: invalid "
                                                         "choice: 'nerf_synthetic'"),
    (["fetch", "chair", "tum_fr1_rpy", "--archive", "x.zip"], "usage error: --archive applies to one dataset"),
    (["fetch", "lego", "--archive", "missing.zip"], "error: --archive missing.zip: no such file"),
    (["fetch", "dss", "--archive", "x.tgz"], "usage error: --archive applies to one dataset published as an archive"),
    (["fetch", "lego", "tum_fr1_rpy", "--sha256", "0" * 64], "usage error: --sha256 applies to one dataset"),
])
def test_usage_and_missing_input_are_one_line(argv, message, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["nsplat"])
    code, _, err = _run(capsys, *argv, "--root", str(tmp_path))
    assert code == 2 and len(err) == 1 and err[0].startswith(message)
    assert _files(tmp_path) == []


EIGHT = ("chair", "drums", "ficus", "hotdog", "lego", "materials", "mic", "ship")


def test_fetch_nerf_synthetic_unpacks_all_eight_scenes_from_one_download(server, tmp_path, capsys):
    root, data = tmp_path / "data", _nerf_zip(EIGHT)
    server.files["nerf_synthetic.zip"] = data
    code, out, err = _run(capsys, "fetch", "nerf_synthetic", "--resolution", "4", "--root", str(root), "--mirror",
                          server.url, "--quiet")
    folder = root / "nerf_synthetic"
    assert code == 0 and err == [] and server.requests == [("nerf_synthetic.zip", None)]  # downloaded once
    assert sorted(p.name for p in folder.iterdir()) == sorted([*EIGHT, *(f"{s}_4" for s in EIGHT)])  # no zip kept
    assert out.count("no checksum is published") == 1 and f"sha256 {_sha(data)}" in out  # the archive's note, once
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        for scene in EIGHT:
            assert f"{scene}: fetched into {folder / scene}\n" in out
            assert f"{scene}_4: written to {folder / scene}_4\n" in out
            assert json.loads((folder / scene / "SOURCE.json").read_text())["dataset"] == scene
            png = (folder / scene / "train" / "r_1.png").read_bytes()
            assert png == zf.read(f"nerf_synthetic/{scene}/train/r_1.png")
            assert load_split(folder / f"{scene}_4", "test").images.shape == (2, 4, 4, 3)
    code, out, _ = _run(capsys, "fetch", "chair", "nerf_synthetic", "--root", str(root), "--mirror", server.url)
    assert code == 0 and len(server.requests) == 1 and out.count("already in") == 8
    assert fetch_mod.expand(["chair", "nerf_synthetic", "dss"]) == [*EIGHT, "dss"]


def test_scenes_by_name_share_one_download_and_resume_another_scenes(server, tmp_path, monkeypatch, capsys):
    """Two scenes named in one command: one download. A download cut off while fetching lego is resumed by a later
    command for another scene, and the scene fetched as ``lego`` is laid out as before."""
    root, data = tmp_path / "data", _nerf_zip(EIGHT)
    server.files["nerf_synthetic.zip"] = data
    code, out, _ = _run(capsys, "fetch", "ship", "chair", "--root", str(root), "--mirror", server.url, "--quiet")
    assert code == 0 and server.requests == [("nerf_synthetic.zip", None)]
    assert sorted(p.name for p in (root / "nerf_synthetic").iterdir()) == ["chair", "ship"]
    server.cut["nerf_synthetic.zip"] = len(data) // 3
    code, _, err = _run(capsys, "fetch", "lego", "--root", str(root), "--mirror", server.url, "--quiet")
    assert code == 2 and "resume" in err[0] and (root / "nerf_synthetic" / "lego.part").is_dir()
    code, out, err = _run(capsys, "fetch", "mic", "--root", str(root), "--mirror", server.url, "--quiet")
    assert code == 0 and err == [] and server.requests[-1] == ("nerf_synthetic.zip", f"bytes={len(data) // 3}-")
    assert sorted(p.name for p in (root / "nerf_synthetic").iterdir()) == ["chair", "mic", "ship"]
    # configs/nerf_synthetic.yaml with data.scene=chair reads the scene's <scene>_400 copy (here the 8² originals)
    monkeypatch.setenv("NSPLAT_DATA", str(root))
    shutil.copytree(root / "nerf_synthetic" / "chair", root / "nerf_synthetic" / "chair_400")
    cfg = load_config(Config, read_yaml(REPO / "configs" / "nerf_synthetic.yaml"), ["data.scene=chair",
                                                                                    "data.resolution=8"])
    views = load_views(cfg, "train", torch.device("cpu"))
    assert views.images.shape == (2, SIDE, SIDE, 3) and cfg.data.root == "$NSPLAT_DATA/nerf_synthetic/chair_400"
    with pytest.raises(ConfigError, match="data.scene: drums: no transforms_train.json in .*; fetch the scene with "
                                          "`nsplat data fetch drums --resolution 400`"):
        load_views(load_config(Config, read_yaml(REPO / "configs" / "nerf_synthetic.yaml"), ["data.scene=drums"]),
                   "train", torch.device("cpu"))
    code, out, _ = _run(capsys, "prepare", "mic", "--resolution", "4", "--root", str(root), "--quiet")
    mic4 = root / "nerf_synthetic" / "mic_4"
    assert code == 0 and f"mic_4: written to {mic4}" in out
    small, ref = load_split(mic4, "train"), load_split(root / "nerf_synthetic" / "mic", "train", resolution=4)
    assert torch.allclose(small.images, ref.images, atol=2.5 / 255) and torch.allclose(small.Ks, ref.Ks)


def test_a_failure_in_one_scene_keeps_the_scenes_before_it_whole(server, tmp_path, monkeypatch, capsys):
    root = tmp_path / "data"
    server.files["nerf_synthetic.zip"] = _nerf_zip(EIGHT)

    def fill_disk(zf: zipfile.ZipFile, info: zipfile.ZipInfo, target: Path) -> None:
        if "/hotdog/" in info.filename:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(target))
        extract(zf, info, target)

    extract = archives_mod.extract_member
    monkeypatch.setattr(archives_mod, "extract_member", fill_disk)
    code, out, err = _run(capsys, "fetch", "nerf_synthetic", "--root", str(root), "--mirror", server.url, "--quiet")
    assert code == 2 and len(err) == 1 and err[0].startswith("error: disk full")
    assert sorted(p.name for p in (root / "nerf_synthetic").iterdir()) == ["chair", "drums", "ficus"]
    assert all(f"{s}: fetched into" in out for s in ("chair", "drums", "ficus"))
    for scene in ("chair", "drums", "ficus"):
        fetch_mod.check_scene(root / "nerf_synthetic" / scene, scene)


def test_a_missing_file_names_the_manual_source(server, tmp_path, capsys):
    del server.files["nerf_synthetic.zip"]
    code, _, err = _run(capsys, "fetch", "lego", "--root", str(tmp_path / "d"), "--mirror", server.url)
    assert code == 2 and len(err) == 1 and "HTTP 404" in err[0] and "pass --archive FILE" in err[0]
    assert not (tmp_path / "d").exists()


def test_archive_downloaded_by_hand(server, tmp_path, capsys):
    archive = tmp_path / "nerf_synthetic.zip"
    archive.write_bytes(server.files["nerf_synthetic.zip"])
    sha = _sha(archive.read_bytes())
    code, out, _ = _run(capsys, "fetch", "lego", "--root", str(tmp_path / "d"), "--archive", str(archive),
                        "--sha256", sha.upper())
    assert code == 0 and "no checksum" not in out and server.requests == []
    assert (tmp_path / "d" / "nerf_synthetic" / "lego" / "transforms_val.json").is_file() and archive.is_file()


def test_the_published_checksums_are_enforced_by_python_m(server, tmp_path):
    """``python -m nsplat.data`` with the real manifest: the fixture PLYs are not the published files."""
    env = {**os.environ, "NSPLAT_DATA": str(tmp_path / "d"), "NSPLAT_DATA_MIRROR": server.url}
    proc = subprocess.run([sys.executable, "-m", "nsplat.data", "fetch", "dss"], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.splitlines() == [proc.stderr.strip()] and "checksum mismatch for bunny-8000.ply" in proc.stderr
    assert "expected sha256 bec459fd076e3ee8871d1d23346222081d9689a8a7a71133e4f4855b5c7283a0" in proc.stderr
    assert not (tmp_path / "d").exists()


def test_data_root_defaults_to_the_user_data_folder(tmp_path, monkeypatch):
    monkeypatch.delenv("NSPLAT_DATA", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path))
    assert data_root() == tmp_path / "nsplat"
    monkeypatch.delenv("XDG_DATA_HOME")
    assert data_root() == Path.home() / ".local" / "share" / "nsplat"
    assert resolve("$NSPLAT_DATA/dss_pointclouds") == data_root() / "dss_pointclouds"
    monkeypatch.setenv("NSPLAT_DATA", str(tmp_path / "d"))
    assert data_root() == tmp_path / "d" and resolve("configs") == REPO / "configs"


@pytest.mark.parametrize("name, camera, sequence", [
    ("tum_fr1_rpy", 1, "rpy"), ("tum_fr1_desk", 1, "desk"), ("tum_fr1_xyz", 1, "xyz"), ("tum_fr1_room", 1, "room"),
    ("tum_fr2_xyz", 2, "xyz"), ("tum_fr3_long_office_household", 3, "long_office_household"),
])
def test_tum_sequences_follow_the_published_url_scheme(name, camera, sequence):
    folder = f"rgbd_dataset_freiburg{camera}_{sequence}"
    ds = fetch_mod.DATASETS[name]
    assert ds.dest == f"rgbd/{folder}" and ds.scene == folder and ds.layout == "tum"
    assert [(r.name, r.url, r.sha256) for r in ds.files] == [
        (f"{folder}.tgz", f"https://cvg.cit.tum.de/rgbd/dataset/freiburg{camera}/{folder}.tgz", None)]


def test_fetch_tum_sequence_resumes_verifies_and_records_its_source(server, tmp_path, capsys):
    root, tgz = tmp_path / "data", _tgz(_tum_files())
    server.files[f"{TUM}.tgz"] = tgz
    server.cut[f"{TUM}.tgz"] = len(tgz) // 3
    code, _, err = _run(capsys, "fetch", "tum_fr1_rpy", "--root", str(root), "--mirror", server.url, "--quiet")
    assert code == 2 and len(err) == 1 and "resume" in err[0]
    code, out, err = _run(capsys, "fetch", "tum_fr1_rpy", "--root", str(root), "--mirror", server.url, "--quiet")
    dest = root / "rgbd" / TUM
    assert code == 0 and err == [] and f"tum_fr1_rpy: fetched into {dest}" in out
    assert f"sha256 {_sha(tgz)}" in out and "no checksum is published" in out and "gzip CRC-32" in out
    assert server.requests == [(f"{TUM}.tgz", None), (f"{TUM}.tgz", f"bytes={len(tgz) // 3}-")]
    assert [p.name for p in (root / "rgbd").iterdir()] == [TUM]  # no .part left
    assert sorted(p.name for p in dest.iterdir()) == ["SOURCE.json", "accelerometer.txt", "depth", "depth.txt",
                                                      "groundtruth.txt", "rgb", "rgb.txt"]
    for name, data in _tum_files().items():
        if data is not None:
            assert (root / "rgbd" / name).read_bytes() == data
    depth = sorted((dest / "depth").iterdir())
    assert len(depth) == 3 and iio.imread(depth[0]).dtype == np.uint16
    assert json.loads((dest / "SOURCE.json").read_text()) == {"dataset": "tum_fr1_rpy", "files": [{
        "file": f"{TUM}.tgz", "url": f"https://cvg.cit.tum.de/rgbd/dataset/freiburg1/{TUM}.tgz",
        "sha256": _sha(tgz), "bytes": len(tgz), "checksum": "none published"}]}
    code, out, _ = _run(capsys, "fetch", "tum_fr1_rpy", "--root", str(root), "--mirror", server.url)
    assert code == 0 and f"tum_fr1_rpy: already in {dest}" in out and len(server.requests) == 2


def test_tum_archive_downloaded_by_hand(tmp_path, capsys):
    folder = "rgbd_dataset_freiburg1_desk"
    archive = tmp_path / f"{folder}.tgz"
    archive.write_bytes(_tgz(_tum_files(folder)))
    code, out, err = _run(capsys, "fetch", "tum_fr1_desk", "--root", str(tmp_path / "d"), "--archive", str(archive),
                          "--sha256", _sha(archive.read_bytes()))
    dest = tmp_path / "d" / "rgbd" / folder
    assert code == 0 and err == [] and f"tum_fr1_desk: fetched into {dest}" in out and "no checksum" not in out
    assert json.loads((dest / "SOURCE.json").read_text())["files"][0]["url"] == str(archive) and archive.is_file()
    done = fetch_mod.fetch("tum_fr1_desk", tmp_path / "d", archive=archive, progress=False)
    assert done.already and done.dest == dest


def _flip(data: bytes) -> bytes:
    """``data`` with one byte in the middle of the compressed stream changed."""
    mid = len(data) // 2
    return data[:mid] + bytes([data[mid] ^ 0x55]) + data[mid + 1:]


def _without(name: str) -> dict[str, bytes | None]:
    files = _tum_files()
    del files[f"{TUM}/{name}"]
    return files


@pytest.mark.parametrize("archive, message", [
    (_tgz(_tum_files())[:-100], "corrupt archive"),
    (_flip(_tgz(_tum_files())), "corrupt archive"),
    (b"PK\x03\x04 not a tgz" * 10, "not a readable .tgz (gzip-compressed tar) archive"),
    (_tgz(_tum_files("rgbd_dataset_freiburg1_xyz")), f"no {TUM}/ folder in the archive"),
    (_tgz(_without(f"rgb/{1305031790.6 + 1 / 30:.6f}.png")), f"rgb.txt names rgb/{1305031790.6 + 1 / 30:.6f}.png, "
                                                             f"which is missing"),
    (_tgz(_without("depth.txt")), "no readable depth.txt"),
    (_tgz(_without("groundtruth.txt")), "no groundtruth.txt"),
    (_tgz({**_tum_files(), "../evil": b"x"}), "unsafe member name '../evil'"),
    (_tgz({**_tum_files(), f"{TUM}/../../evil": b"x"}), f"unsafe member name '{TUM}/../../evil'"),
    (_tgz({**_tum_files(), "/tmp/evil": b"x"}), "unsafe member name '/tmp/evil'"),
    (_tgz(_tum_files(), {f"{TUM}/rgb/evil.png": "/etc/passwd"}), "is neither a file nor a folder"),
], ids=["truncated", "flipped-byte", "not-a-tgz", "other-folder", "missing-frame", "no-depth-list", "no-groundtruth",
        "dotdot", "inner-dotdot", "absolute", "symlink"])
def test_bad_tum_archives_are_one_line_and_leave_nothing(archive, message, server, tmp_path, capsys):
    root = tmp_path / "data"
    server.files[f"{TUM}.tgz"] = archive
    code, _, err = _run(capsys, "fetch", "tum_fr1_rpy", "--root", str(root), "--mirror", server.url, "--quiet")
    assert code == 2 and len(err) == 1 and err[0].startswith("error: ") and message in err[0], err
    assert _files(root) == [] and not list(tmp_path.rglob("evil*"))

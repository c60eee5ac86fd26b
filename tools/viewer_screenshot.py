"""Screenshot of the web viewer with headless Chromium (docs/images/viewer/*.png). Not run in CI.

    apt-get install -y chromium          # Debian's package
    python -m tools.viewer_screenshot [--run DIR] [--out docs/images/viewer/viewer.png]

Without ``--run`` it first trains a small run of the main job (``python train.py`` with a short
budget: 4 stage-1 epochs, 60 stage-2 steps; a few minutes on 2 cores). It then serves the run on a
free local port, opens the page in headless Chromium (WebGL through SwiftShader, i.e. on the CPU),
driven over the DevTools protocol: it waits in real time until the server has sent the browser a
full-quality render, dismisses the "software WebGL" notice and saves a PNG of the window.
"""
from __future__ import annotations

import argparse
import base64
import dataclasses
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

from benchmarks.common import IMAGES, REPO
from nsplat.cli import main as train_main
from nsplat.viewer.config import ViewerConfig
from nsplat.viewer.runs import load_run
from nsplat.viewer.server import ViewerServer, free_port

TRAIN = ["geometry.optim.epochs=4", "neural.steps=60", "log.validate=0", "log.progress=false"]


def _devtools(port: int, timeout: float = 30.0) -> str:
    """WebSocket address of the first page target of a Chromium listening on ``port``."""
    t_end = time.time() + timeout
    while time.time() < t_end:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=2) as r:
                pages = [t for t in json.load(r) if t.get("type") == "page"]
            if pages:
                return pages[0]["webSocketDebuggerUrl"]
        except OSError:
            pass
        time.sleep(0.3)
    raise RuntimeError("chromium did not open its DevTools port")


class _Cdp:
    """Minimal Chrome DevTools Protocol client (synchronous)."""

    def __init__(self, url: str) -> None:
        from websockets.sync.client import connect

        self.ws, self.n = connect(url, max_size=64 * 2**20), 0

    def __call__(self, method: str, **params) -> dict:
        self.n += 1
        self.ws.send(json.dumps({"id": self.n, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=60))
            if msg.get("id") == self.n:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})


def screenshot(run: Path, out: Path, width: int = 1200, height: int = 760, mode: str = "rgb",
               resolution: int = 384, samples: int = 16) -> Path:
    """Serve ``run`` and save a headless-Chromium screenshot of the viewer page to ``out``."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("chromium not found (apt-get install -y chromium)")
    model = load_run(run)
    server = ViewerServer(model, ViewerConfig(port=free_port(), resolution=resolution, render={"samples": samples}))
    server.settings = dataclasses.replace(server.settings, mode=mode)
    server.progressive = False  # the screenshot waits for the full render anyway
    debug_port = free_port()
    profile = tempfile.mkdtemp(prefix="nsplat-chromium-")
    proc = subprocess.Popen([chromium, "--headless=new", "--no-sandbox", "--use-angle=swiftshader",
                             "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", f"--user-data-dir={profile}",
                             f"--window-size={width},{height}", f"--remote-debugging-port={debug_port}",
                             "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        cdp = _Cdp(_devtools(debug_port))
        cdp("Page.enable")
        cdp("Page.navigate", url=server.url)
        t_end = time.time() + 120
        while time.time() < t_end and not any(st.full and st.key for st in server._clients.values()):
            time.sleep(0.5)
        if not server._clients:
            raise RuntimeError("the page never reported its camera to the server")
        time.sleep(3.0)  # let the client decode and draw the background image
        cdp("Runtime.evaluate", expression="document.querySelectorAll('.mantine-Notification-root')"
                                           ".forEach(e => e.remove())")
        time.sleep(0.5)
        png = base64.b64decode(cdp("Page.captureScreenshot", format="png")["data"])
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(png)
    finally:
        proc.terminate()
        proc.wait(timeout=20)
        server.close()
        shutil.rmtree(profile, ignore_errors=True)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", type=Path, default=None, help="run folder to show (default: train a small one)")
    p.add_argument("--out", type=Path, default=IMAGES / "viewer" / "viewer.png")
    p.add_argument("--mode", default="rgb", help="rgb, features, alpha or depth")
    args = p.parse_args()
    run = args.run
    if run is None:
        run = REPO / "runs" / "viewer-screenshot"
        if not (run / "checkpoints" / "latest").is_file():
            if train_main(["--run", str(run), *TRAIN]) != 0:
                return 1
    path = screenshot(run, args.out, mode=args.mode)
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

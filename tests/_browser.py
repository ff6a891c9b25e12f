"""Test helpers for `fgjax view`: a websocket client that speaks viser's wire format, and screenshots of a page in
a headless Chromium driven over the DevTools protocol (no browser package needed: `websockets` comes with viser)."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import imageio.v3 as iio
import msgspec
import numpy as np
import viser
import zstandard
from websockets.sync.client import connect

CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--enable-unsafe-swiftshader", "--hide-scrollbars"]


def chromium() -> str | None:
    """Path of a Chromium (or Chrome) executable, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def decode_frame(frame: bytes) -> tuple[list[dict], list[bytes]]:
    """(messages, binary buffers) of one server -> client frame: [8 B msgpack size][8 B compressed size][zstd
    msgpack][binary buffers, each 8-byte aligned]; a numpy array in a message is {"__binary_index": i, "dtype"}."""
    n_inner, n_comp = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
    inner = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(frame[16:16 + n_comp],
                                                                          max_output_size=n_inner))
    off, bufs = 16 + n_comp, []
    for n in inner["binaryBufferLengths"]:
        off += (8 - off % 8) % 8
        bufs.append(frame[off:off + n])
        off += n
    return inner["messages"], bufs


def splat_centers(buffer: bytes) -> np.ndarray:
    """[N, 3] centres of a Gaussian-splat buffer (8 uint32 per Gaussian, the first three the float32 centre)."""
    return np.frombuffer(buffer, np.uint32).reshape(-1, 8)[:, :3].copy().view(np.float32)


class ViserClient:
    """A minimal viser client: receives messages; moves a GUI input as a browser would."""

    def __init__(self, url: str, timeout: float = 30.0):
        self.ws = connect(url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None, open_timeout=timeout)
        self.messages: list[tuple[dict, list[bytes]]] = []
        # the server counts a client as connected once it reports its camera (as a browser does at once)
        self.send({"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, 0.0, 0.0],
                   "fov": 1.0, "near": 0.01, "far": 100.0, "image_height": 480, "image_width": 640,
                   "look_at": [0.0, 0.0, 1.0], "up_direction": [0.0, 0.0, 1.0]})

    def send(self, message: dict) -> None:
        self.ws.send(msgspec.msgpack.encode(message))

    def receive(self, until, timeout: float) -> list[tuple[dict, list[bytes]]]:
        """Messages [(message, its frame's buffers)] received until ``until(all so far)`` is true or ``timeout``."""
        end = time.time() + timeout
        while not until(self.messages) and time.time() < end:
            try:
                frame = self.ws.recv(timeout=max(0.05, min(1.0, end - time.time())))
            except TimeoutError:
                continue
            msgs, bufs = decode_frame(frame)
            self.messages += [(m, bufs) for m in msgs]
        return self.messages

    def of_type(self, kind: str) -> list[tuple[dict, list[bytes]]]:
        return [(m, b) for m, b in self.messages if m["type"] == kind]

    def gui(self, label: str) -> dict:
        """The creation message of the GUI input with this label."""
        return next(m for m, _ in self.messages if m["type"].startswith("Gui") and m.get("props", {}).get("label")
                    == label)

    def set_value(self, label: str, value) -> None:
        self.send({"type": "GuiUpdateMessage", "uuid": self.gui(label)["uuid"], "updates": {"value": value}})

    def close(self) -> None:
        self.ws.close()


class Browser:
    """A headless Chromium on a fresh profile, one page, driven over the DevTools protocol."""

    def __init__(self, exe: str, width: int = 960, height: int = 640):
        self.profile = Path(tempfile.mkdtemp(prefix="fgjax-chromium-"))
        self.proc = subprocess.Popen([exe, *CHROMIUM_FLAGS, f"--user-data-dir={self.profile}",
                                      f"--window-size={width},{height}", "--remote-debugging-port=0", "about:blank"],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file = self.profile / "DevToolsActivePort"
        end = time.time() + 30
        while not (port_file.exists() and port_file.read_text().strip()) and time.time() < end:
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
        url = next(p["webSocketDebuggerUrl"] for p in pages if p["type"] == "page")
        self.ws = connect(url, max_size=None)
        self.next_id = 0

    def call(self, method: str, **params) -> dict:
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            reply = json.loads(self.ws.recv(timeout=60))
            if reply.get("id") == self.next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def screenshot(self) -> np.ndarray:
        """[H, W, 3] uint8 of the page as it is now."""
        png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return iio.imread(png)[..., :3]

    def close(self) -> None:
        try:
            self.ws.close()
        finally:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
            shutil.rmtree(self.profile, ignore_errors=True)

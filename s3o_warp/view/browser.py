"""A headless Chromium looking at a page, driven through the DevTools protocol: screenshots of the viewer for the
tests (the page draws the mesh) and the README's picture. Needs a Chromium binary (Debian's ``chromium``) and
``websockets`` (which viser brings); WebGL runs in software (SwiftShader), so no GPU is needed.
"""

from __future__ import annotations

import base64
import io
import itertools
import json
import logging
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")

HIDE_NOTICES = "document.querySelectorAll('.mantine-Notification-root').forEach(e => e.remove())"
"""JavaScript that removes viser's notices (such as "Software WebGL rendering detected") from the page."""


def find_chromium() -> str | None:
    """The path of a Chromium (or Chrome) binary on PATH, or None."""
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


class HeadlessPage:
    """``url`` open in a headless Chromium of ``size`` (width, height) pixels; use as a context manager.

    Raises:
        FileNotFoundError: no Chromium binary.
        TimeoutError: Chromium did not start (or open its page) within ``timeout`` seconds.
    """

    def __init__(self, url: str, size: tuple[int, int] = (1280, 800), binary: str | None = None,
                 timeout: float = 30.0):
        from websockets.sync.client import connect

        binary = binary or find_chromium()
        if binary is None:
            raise FileNotFoundError("no Chromium binary found (install Debian's chromium)")
        self._profile = Path(tempfile.mkdtemp(prefix="s3o-view-chromium-"))
        args = [binary, "--headless", "--no-sandbox", "--no-first-run", "--no-default-browser-check",
                "--hide-scrollbars", "--mute-audio", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                f"--window-size={size[0]},{size[1]}", "--remote-debugging-port=0",
                f"--user-data-dir={self._profile}", url]
        self._log = open(self._profile / "chromium.log", "wb")
        self.proc = subprocess.Popen(args, stdout=self._log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        self._ids = itertools.count(1)
        try:
            port = self._devtools_port(timeout)
            ws_url = self._page_target(port, timeout)
            self.ws = connect(ws_url, max_size=None, open_timeout=timeout)
        except BaseException:
            self.close()
            raise

    def _devtools_port(self, timeout: float) -> int:
        """The DevTools port Chromium picked (it writes it into its profile folder)."""
        f = self._profile / "DevToolsActivePort"
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"chromium exited with code {self.proc.returncode} before it opened the page")
            try:
                lines = f.read_text().split()
                if lines:
                    return int(lines[0])
            except (OSError, ValueError):
                pass
            time.sleep(0.05)
        raise TimeoutError(f"chromium did not start within {timeout:.0f} s")

    @staticmethod
    def _page_target(port: int, timeout: float) -> str:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
                    pages = [t for t in json.load(r) if t.get("type") == "page"]
                if pages:
                    return pages[0]["webSocketDebuggerUrl"]
            except OSError:
                pass
            time.sleep(0.05)
        raise TimeoutError(f"chromium opened no page within {timeout:.0f} s")

    def call(self, method: str, **params) -> dict:
        """One DevTools command; returns its result (events in between are dropped)."""
        i = next(self._ids)
        self.ws.send(json.dumps({"id": i, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=60))
            if msg.get("id") == i:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def evaluate(self, js: str):
        """The value of a JavaScript expression in the page."""
        return self.call("Runtime.evaluate", expression=js, returnByValue=True).get("result", {}).get("value")

    def screenshot(self) -> np.ndarray:
        """(H, W, 3) uint8 RGB picture of the page as it is now."""
        from PIL import Image

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

    def wait_for(self, check, timeout: float = 30.0, every: float = 0.1) -> tuple[np.ndarray, bool]:
        """Screenshots until ``check(picture)`` holds or ``timeout`` seconds pass: (the last picture, whether it
        held)."""
        end = time.monotonic() + timeout
        while True:
            img = self.screenshot()
            if check(img):
                return img, True
            if time.monotonic() > end:
                return img, False
            time.sleep(every)

    def close(self) -> None:
        ws = getattr(self, "ws", None)
        if ws is not None:
            ws.close()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> "HeadlessPage":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def colour_pixels(img: np.ndarray, rgb: tuple[int, int, int], tol: float = 0.25) -> int:
    """How many pixels of ``img`` have the hue of ``rgb`` however lit: each channel, over the brightest, within
    ``tol`` of ``rgb``'s own ratios (and not near black)."""
    x = img.astype(np.float32)
    peak = x.max(-1, keepdims=True)
    ref = np.asarray(rgb, np.float32)
    ref = ref / max(float(ref.max()), 1.0)
    ok = (np.abs(x / np.maximum(peak, 1.0) - ref) < tol).all(-1) & (peak[..., 0] > 40)
    return int(ok.sum())

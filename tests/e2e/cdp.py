"""A minimal headless-Chromium driver over the DevTools protocol, for tests of live pages (the viewer).

The report test uses Chromium's command line (``--screenshot``); a page that draws frames from a websocket
needs real time instead of virtual time, and a test must be able to wait for a frame. This opens a page,
records the URLs it requests (``Network.requestWillBeSent``: the page's own requests, not the browser's
background services) and takes screenshots on demand. It needs only ``websockets`` (a viser dependency).
"""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import socket
import subprocess
import time
import urllib.request
from pathlib import Path

import numpy as np


def find_chromium() -> str | None:
    for c in ("/usr/bin/chromium", shutil.which("chromium"), shutil.which("chromium-browser")):
        if c and os.path.exists(c):
            return c
    return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Browser:
    """Headless Chromium with one page; use as a context manager."""

    def __init__(self, executable: str, profile: Path, width: int = 800, height: int = 600):
        self.port = _free_port()
        flags = ["--headless", "--no-sandbox", "--disable-gpu", "--use-gl=swiftshader", "--enable-unsafe-swiftshader",
                 "--no-first-run", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--disable-site-isolation-trials", "--disable-features=site-per-process",
                 f"--window-size={width},{height}", f"--user-data-dir={profile}",
                 f"--remote-debugging-port={self.port}",
                 # every host but this machine is unresolvable: a page that needs the internet shows it
                 "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE localhost, EXCLUDE 127.0.0.1", "about:blank"]
        self.proc = subprocess.Popen([executable, *flags], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        self.requests: list[str] = []
        self.events: list[str] = []
        self._id = 0
        self.ws = None

    def __enter__(self) -> Browser:
        from websockets.sync.client import connect

        deadline = time.monotonic() + 60
        target = None
        while time.monotonic() < deadline and target is None:
            if self.proc.poll() is not None:
                raise RuntimeError(f"chromium exited ({self.proc.returncode}): {self.proc.stderr.read()[-500:]!r}")
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/json/list", timeout=5) as r:
                    pages = [t for t in json.loads(r.read()) if t.get("type") == "page"]
                target = pages[0] if pages else None
            except OSError:
                time.sleep(0.2)
        if target is None:
            self.close()
            raise RuntimeError("chromium's DevTools endpoint did not come up within 60 s")
        self.ws = connect(target["webSocketDebuggerUrl"], max_size=64 * 1024 * 1024, open_timeout=30)
        self.call("Network.enable")
        self.call("Page.enable")
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self.ws is not None:
            self.ws.close()
            self.ws = None
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()

    def _receive(self, deadline: float) -> dict:
        msg = json.loads(self.ws.recv(timeout=max(deadline - time.monotonic(), 0.01)))
        if msg.get("method") == "Network.requestWillBeSent":
            self.requests.append(msg["params"]["request"]["url"])
        elif msg.get("method") == "Network.webSocketCreated":
            self.requests.append(msg["params"]["url"])
        if "method" in msg:
            self.events.append(msg["method"])
        return msg

    def call(self, method: str, timeout: float = 60.0, **params) -> dict:
        """Send one command and return its result (recording the page's requests seen meanwhile)."""
        self._id += 1
        my_id = self._id
        self.ws.send(json.dumps({"id": my_id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout
        while True:
            msg = self._receive(deadline)
            if msg.get("id") == my_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def goto(self, url: str, timeout: float = 60.0) -> None:
        """Navigate and wait for the load event."""
        self.events.clear()
        self.call("Page.navigate", url=url)
        deadline = time.monotonic() + timeout
        while "Page.loadEventFired" not in self.events:
            self._receive(deadline)

    def screenshot(self) -> np.ndarray:
        """[H,W,3] float32 in [0, 1] of the page as it is now."""
        from PIL import Image

        png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float32) / 255.0

    def wait_for(self, predicate, timeout: float = 120.0, interval: float = 0.5) -> np.ndarray:
        """Screenshots until ``predicate(image)`` holds; returns that image (AssertionError on timeout)."""
        deadline = time.monotonic() + timeout
        img = self.screenshot()
        while not predicate(img):
            if time.monotonic() > deadline:
                raise AssertionError(f"the page did not reach the expected state within {timeout:.0f} s")
            time.sleep(interval)
            img = self.screenshot()
        return img

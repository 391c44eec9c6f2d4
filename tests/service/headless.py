"""A real headless Chromium driven over the DevTools protocol (websockets): load a page,
collect console errors and uncaught exceptions, evaluate JS, take a screenshot.

Chromium comes from Debian (``make browser``); :func:`chromium_path` is ``None`` when it
is not installed, and the tests skip saying so.
"""
from __future__ import annotations

import base64
import contextlib
import itertools
import json
import os
import re
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

BROWSERS = ("chromium", "chromium-browser", "google-chrome")


def chromium_path() -> str | None:
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    return None


# Chromium writes "<port>\n/devtools/browser/<uuid>"; the file can be seen half-written
_PORT_FILE = re.compile(r"\d+\n/devtools/browser/[0-9a-f-]{36}\s*$")


def _port_file_complete(port_file: Path) -> bool:
    try:
        return _PORT_FILE.match(port_file.read_text()) is not None
    except FileNotFoundError:
        return False


class Page:
    """One headless browser with one page. Use as a context manager."""

    # generous: a loaded 2-core CI machine starts Chromium slowly; a limit, not a pace
    def __init__(self, binary: str, timeout_s: float = 180.0) -> None:
        self.binary = binary
        self.timeout_s = timeout_s
        self.errors: list[str] = []
        self._ids = itertools.count(1)

    def __enter__(self) -> "Page":
        from websockets.sync.client import connect

        # the profile is the browser's scratch: a helper process still writing to it as it is
        # removed must not fail the test that used the page (seen under load: 'Default' not empty)
        self._dir = tempfile.TemporaryDirectory(prefix="adaptnav-chromium-", ignore_cleanup_errors=True)
        self.proc = subprocess.Popen(
            [self.binary, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
             "--disable-extensions", "--disable-background-networking", "--remote-debugging-port=0",
             f"--user-data-dir={self._dir.name}", "--window-size=1280,1600", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True)  # its own process group: its helper processes end with it
        port_file = Path(self._dir.name) / "DevToolsActivePort"
        deadline = time.monotonic() + self.timeout_s
        while not _port_file_complete(port_file):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"{self.binary} did not start (exit {self.proc.poll()})")
            time.sleep(0.05)  # waiting for the browser to write its port file, not pacing anything
        port, path = port_file.read_text().splitlines()[:2]
        self._stack = contextlib.ExitStack()
        self.ws = self._stack.enter_context(connect(f"ws://127.0.0.1:{port}{path}", max_size=None,
                                                    open_timeout=self.timeout_s))
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in ("Page", "Runtime", "Log"):
            self.call(f"{domain}.enable", session=True)
        return self

    def __exit__(self, *exc) -> None:
        try:
            self._stack.close()
        finally:
            self._signal_group(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                pass
            self._signal_group(signal.SIGKILL)  # the renderer, GPU and utility processes too
            self.proc.wait()
            self._dir.cleanup()

    def _signal_group(self, sig: int) -> None:
        try:
            os.killpg(self.proc.pid, sig)
        except ProcessLookupError:
            pass

    # -- protocol ------------------------------------------------------------------------
    def _event(self, msg: dict) -> None:
        method, p = msg.get("method"), msg.get("params", {})
        if method == "Runtime.exceptionThrown":
            d = p["exceptionDetails"]
            self.errors.append(f"exception: {d.get('exception', {}).get('description') or d.get('text')}")
        elif method == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
            self.errors.append("console." + p["type"] + ": " + " ".join(str(a.get("value", a.get("description")))
                                                                       for a in p.get("args", [])))
        elif method == "Log.entryAdded" and p["entry"].get("level") == "error":
            self.errors.append(f"log: {p['entry'].get('text')} {p['entry'].get('url', '')}")

    def call(self, method: str, session: bool = False, **params) -> dict:
        msg_id = next(self._ids)
        msg = {"id": msg_id, "method": method, "params": params}
        if session:
            msg["sessionId"] = self.session
        self.ws.send(json.dumps(msg))
        return self._wait(lambda m: m.get("id") == msg_id)["result"]

    def _wait(self, pred) -> dict:
        deadline = time.monotonic() + self.timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError("no answer from the browser")
            msg = json.loads(self.ws.recv(timeout=remaining))
            if "method" in msg:
                self._event(msg)
            if pred(msg):
                if "error" in msg:
                    raise RuntimeError(f"DevTools: {msg['error']}")
                return msg

    # -- what the tests use --------------------------------------------------------------
    def load(self, url: str) -> None:
        """Navigate and wait for the load event (console errors are collected meanwhile)."""
        self.call("Page.navigate", session=True, url=url)
        self._wait(lambda m: m.get("method") == "Page.loadEventFired")

    def evaluate(self, expression: str):
        res = self.call("Runtime.evaluate", session=True, expression=expression, returnByValue=True)
        return res["result"].get("value")

    def screenshot(self, path: Path) -> Path:
        data = self.call("Page.captureScreenshot", session=True, format="png", captureBeyondViewport=True)["data"]
        path.write_bytes(base64.b64decode(data))
        return path

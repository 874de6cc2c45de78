"""Headless Chromium driven over the Chrome DevTools Protocol (CDP): what the web-page tests, the
frame-age benchmark (tools/bench_web.py) and the docs' screenshot use.

    with HeadlessChromium(width=1280, height=800) as browser:
        browser.open("http://127.0.0.1:8080/avatar")
        browser.wait_for("window.stgStats && window.stgStats.avatar.shown >= 3", timeout=60)
        png = browser.screenshot()                     # PNG bytes of the page as Chromium drew it

    python tools/headless_chromium.py URL out.png [--wait JS] [--width W --height H]

Chromium runs with --headless --no-sandbox --disable-gpu --disable-background-networking
--disable-component-update --disable-sync --no-first-run, a fresh --user-data-dir (removed on
close) and --remote-debugging-port=0 (the port it picked is read from DevToolsActivePort), in a
process group of its own: closing asks it to quit, then kills the whole group (the renderer,
GPU and zygote children included), so nothing survives a test. The CDP client is the
``websockets`` package's synchronous one.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

BINARIES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-dev-shm-usage",
    "--hide-scrollbars",
    "--mute-audio",
)


class BrowserError(RuntimeError):
    """Chromium is missing, did not start, or a page did not do what was waited for."""


def find_chromium() -> str | None:
    """Path of a Chromium (or Chrome) binary on PATH, or $STG_CHROMIUM; None if there is none."""
    explicit = os.environ.get("STG_CHROMIUM")
    if explicit:
        return explicit if shutil.which(explicit) else None
    for name in BINARIES:
        path = shutil.which(name)
        if path:
            return path
    return None


class HeadlessChromium:
    def __init__(
        self, *, width: int = 1280, height: int = 800, binary: str | None = None, timeout: float = 60
    ):
        self.binary = binary or find_chromium()
        if self.binary is None:
            raise BrowserError(f"no Chromium found (tried {', '.join(BINARIES)}; apt-get install chromium)")
        self.width, self.height, self.timeout = width, height, timeout
        self.profile = tempfile.mkdtemp(prefix="stg-chromium-")
        self.process: subprocess.Popen | None = None
        self.ws = None
        self._ids = itertools.count(1)
        self.console: list[str] = []  # console messages and exceptions of the page

    # -- life cycle ---------------------------------------------------------------------------------------

    def start(self) -> HeadlessChromium:
        from websockets.sync.client import connect

        args = [
            self.binary,
            *FLAGS,
            f"--user-data-dir={self.profile}",
            "--remote-debugging-port=0",
            "--remote-debugging-address=127.0.0.1",
            f"--window-size={self.width},{self.height}",
            "about:blank",
        ]
        self.process = subprocess.Popen(
            args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
        )
        active = Path(self.profile) / "DevToolsActivePort"
        deadline = time.monotonic() + self.timeout
        while not (active.is_file() and len(active.read_text().splitlines()) >= 2):
            if self.process.poll() is not None:
                raise BrowserError(f"{self.binary} exited with code {self.process.returncode} at start")
            if time.monotonic() > deadline:
                raise BrowserError(f"{self.binary} did not open its DevTools port in {self.timeout} s")
            time.sleep(0.1)
        port = int(active.read_text().splitlines()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as response:
            targets = json.load(response)
        page = next(t for t in targets if t.get("type") == "page")
        self._stack = contextlib.ExitStack()  # the CDP connection as a context (websockets >= 17.1)
        self.ws = self._stack.enter_context(
            connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=10)
        )
        self.call("Page.enable")
        self.call("Runtime.enable")
        # The viewport exactly width x height (a headless window keeps room for browser UI).
        self.call(
            "Emulation.setDeviceMetricsOverride",
            {"width": self.width, "height": self.height, "deviceScaleFactor": 1, "mobile": False},
        )
        return self

    @property
    def pids(self) -> list[int]:
        """Every process of Chromium's group (for no-orphan checks)."""
        if self.process is None:
            return []
        out = []
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit():
                try:
                    if os.getpgid(int(entry.name)) == self.process.pid:
                        out.append(int(entry.name))
                except OSError:
                    continue
        return out

    def close(self) -> None:
        if self.ws is not None:
            try:
                self.call("Browser.close", timeout=5)
            except Exception:  # it may be gone already; the group kill below still runs
                pass
            try:
                self._stack.close()
            except Exception:
                pass
            self.ws = None
        if self.process is not None:
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                pass
            for sig in (signal.SIGTERM, signal.SIGKILL):
                try:
                    os.killpg(self.process.pid, sig)
                except ProcessLookupError:
                    break
                time.sleep(0.5)
            if self.process.poll() is None:
                self.process.kill()
            self.process.wait(timeout=10)
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> HeadlessChromium:
        try:
            return self.start()
        except BaseException:
            self.close()
            raise

    def __exit__(self, *exc) -> None:
        self.close()

    # -- CDP ------------------------------------------------------------------------------------------------

    def call(self, method: str, params: dict | None = None, timeout: float | None = None) -> dict:
        """Send a CDP command and wait for its result (events in between are kept as console lines)."""
        call_id = next(self._ids)
        self.ws.send(json.dumps({"id": call_id, "method": method, "params": params or {}}))
        deadline = time.monotonic() + (timeout or self.timeout)
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise BrowserError(f"CDP {method}: no answer in {timeout or self.timeout} s")
            msg = json.loads(self.ws.recv(timeout=left))
            if msg.get("id") == call_id:
                if "error" in msg:
                    raise BrowserError(f"CDP {method}: {msg['error']}")
                return msg.get("result", {})
            self._event(msg)

    def _event(self, msg: dict) -> None:
        method = msg.get("method", "")
        params = msg.get("params", {})
        if method == "Runtime.consoleAPICalled":
            args = " ".join(str(a.get("value", a.get("description", ""))) for a in params.get("args", []))
            self.console.append(f"console.{params.get('type')}: {args}")
        elif method == "Runtime.exceptionThrown":
            details = params.get("exceptionDetails", {})
            text = details.get("exception", {}).get("description") or details.get("text", "")
            self.console.append(f"exception: {text}")

    def open(self, url: str) -> None:
        self.call("Page.navigate", {"url": url})

    def evaluate(self, expression: str):
        result = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True})
        if "exceptionDetails" in result:
            raise BrowserError(f"{expression!r} raised: {result['exceptionDetails'].get('text')}")
        return result.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout: float = 60.0, poll_s: float = 0.2):
        """Poll a JavaScript expression until it is truthy; its value. BrowserError with the page's
        console on timeout."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                value = self.evaluate(expression)
            except BrowserError:
                value = None
            if value:
                return value
            if time.monotonic() > deadline:
                console = "\n".join(self.console[-20:]) or "(nothing)"
                raise BrowserError(f"waited {timeout} s for {expression!r}; the page's console:\n{console}")
            time.sleep(poll_s)

    def screenshot(self) -> bytes:
        """PNG of the viewport as Chromium drew it."""
        return base64.b64decode(self.call("Page.captureScreenshot", {"format": "png"})["data"])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Screenshot a page with headless Chromium.")
    parser.add_argument("url")
    parser.add_argument("out", help="PNG file to write")
    parser.add_argument("--wait", default="true", metavar="JS", help="take it once this expression is true")
    parser.add_argument("--settle", type=float, default=0.5, metavar="S", help="then wait this long")
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=800)
    parser.add_argument("--timeout", type=float, default=60.0)
    args = parser.parse_args(argv)
    with HeadlessChromium(width=args.width, height=args.height) as browser:
        browser.open(args.url)
        browser.wait_for(args.wait, timeout=args.timeout)
        time.sleep(args.settle)
        Path(args.out).write_bytes(browser.screenshot())
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A headless Chromium driven over the DevTools protocol, for the browser tests.

The browser talks over a pipe (``--remote-debugging-pipe``: the child reads
commands on fd 3 and writes replies on fd 4, each a JSON message ended by a
NUL byte), so no port is opened and no websocket library is needed. The
browser is Debian's ``chromium`` (see :func:`browser.chromium`, which skips or
fails the test when it cannot be had).

Usage::

    with Page(tmp_path / "profile") as page:
        page.open(html_path)
        assert page.eval("1 + 1") == 2
        page.click(200, 300)
        page.screenshot(tmp_path / "shot.png")
"""

from __future__ import annotations

import base64
import json
import os
import select
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

from browser import HEADLESS, chromium

__all__ = ["CDPError", "Page"]


class CDPError(RuntimeError):
    """The browser answered a command with an error, or did not answer in time."""


def _child_fds(read_end: int, write_end: int) -> None:
    # in the child, before exec: fd 3 = the commands it reads, fd 4 = the replies it writes;
    # go through high numbers first so that neither dup2 clobbers the other end
    hi_r = os.dup(read_end)
    hi_w = os.dup(write_end)
    os.dup2(hi_r, 3)
    os.dup2(hi_w, 4)
    os.set_inheritable(3, True)
    os.set_inheritable(4, True)


class Page:
    """One headless Chromium with one page (tab), driven over the DevTools protocol.

    Args:
        profile: A fresh directory for the browser's profile.
        size: Window size in CSS pixels (width, height).
        timeout_s: Time bound of each command [s].
    """

    def __init__(self, profile: Path, size: tuple[int, int] = (1200, 800), timeout_s: float = 60.0):
        self.size = size
        self.timeout_s = timeout_s
        self._next_id = 0
        self._buf = b""
        self._events: list[dict[str, Any]] = []
        self.console: list[str] = []
        self.errors: list[str] = []
        cmd_r, cmd_w = os.pipe()  # we write commands, the browser reads them on fd 3
        rep_r, rep_w = os.pipe()  # the browser writes replies on fd 4, we read them
        args = [
            chromium(),
            *HEADLESS,
            "--allow-file-access-from-files",
            "--remote-debugging-pipe",
            f"--user-data-dir={profile}",
            f"--window-size={size[0]},{size[1]}",
            "about:blank",
        ]
        self._proc = subprocess.Popen(
            args,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            pass_fds=(3, 4),
            preexec_fn=lambda: _child_fds(cmd_r, rep_w),
            start_new_session=True,
        )
        os.close(cmd_r)
        os.close(rep_w)
        self._w = cmd_w
        self._r = rep_r
        try:
            target = self._call("Target.createTarget", {"url": "about:blank"})["targetId"]
            self._session = self._call(
                "Target.attachToTarget", {"targetId": target, "flatten": True}
            )["sessionId"]
            for domain in ("Page", "Runtime"):
                self.call(f"{domain}.enable")
            self.call(
                "Emulation.setDeviceMetricsOverride",
                {"width": size[0], "height": size[1], "deviceScaleFactor": 1, "mobile": False},
            )
        except BaseException:
            self.close()
            raise

    # -- the protocol -------------------------------------------------------------------

    def _send(self, message: dict[str, Any]) -> int:
        self._next_id += 1
        message["id"] = self._next_id
        data = json.dumps(message).encode() + b"\0"
        while data:
            n = os.write(self._w, data)
            data = data[n:]
        return self._next_id

    def _read_message(self, deadline: float) -> dict[str, Any]:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise CDPError("the browser did not answer in time")
            ready, _, _ = select.select([self._r], [], [], left)
            if not ready:
                continue
            chunk = os.read(self._r, 1 << 20)
            if not chunk:
                raise CDPError("the browser closed its DevTools pipe (it exited)")
            self._buf += chunk
        raw, self._buf = self._buf.split(b"\0", 1)
        return json.loads(raw)

    def _wait(self, msg_id: int, timeout_s: float | None = None) -> dict[str, Any]:
        deadline = time.monotonic() + (timeout_s or self.timeout_s)
        while True:
            msg = self._read_message(deadline)
            if msg.get("id") == msg_id:
                if "error" in msg:
                    raise CDPError(f"{msg['error']}")
                return msg.get("result", {})
            self._event(msg)

    def _event(self, msg: dict[str, Any]) -> None:
        method = msg.get("method", "")
        params = msg.get("params", {})
        if method == "Runtime.consoleAPICalled":
            text = " ".join(str(a.get("value", a.get("description", ""))) for a in params["args"])
            self.console.append(f"{params.get('type')}: {text}")
        elif method == "Runtime.exceptionThrown":
            details = params.get("exceptionDetails", {})
            exc = details.get("exception", {})
            self.errors.append(str(exc.get("description") or details.get("text")))
        self._events.append(msg)

    def _call(self, method: str, params: dict[str, Any] | None = None) -> dict[str, Any]:
        return self._wait(self._send({"method": method, "params": params or {}}))

    def call(
        self, method: str, params: dict[str, Any] | None = None, timeout_s: float | None = None
    ) -> dict[str, Any]:
        """Send one command to the page's session and return its result."""
        msg_id = self._send({"method": method, "params": params or {}, "sessionId": self._session})
        return self._wait(msg_id, timeout_s)

    # -- what tests use -----------------------------------------------------------------

    def open(self, path: Path | str, settle_s: float = 0.5) -> None:
        """Load a file (or URL) and wait for its load event, then ``settle_s`` more."""
        url = path if isinstance(path, str) else Path(path).resolve().as_uri()
        self._events.clear()
        self.call("Page.navigate", {"url": url})
        deadline = time.monotonic() + self.timeout_s
        while not any(e.get("method") == "Page.loadEventFired" for e in self._events):
            self._event(self._read_message(deadline))
        time.sleep(settle_s)

    def eval(self, expression: str, timeout_s: float | None = None) -> Any:
        """Evaluate a JavaScript expression in the page (promises awaited); its JSON value."""
        result = self.call(
            "Runtime.evaluate",
            {"expression": expression, "returnByValue": True, "awaitPromise": True},
            timeout_s,
        )
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            exc = details.get("exception", {})
            raise CDPError(f"{expression[:80]!r} threw: {exc.get('description') or details}")
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout_s: float = 30.0, poll_s: float = 0.1) -> Any:
        """Poll ``expression`` until it is truthy; its value. CDPError after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            value = self.eval(expression)
            if value:
                return value
            if time.monotonic() > deadline:
                raise CDPError(f"{expression[:80]!r} still falsy after {timeout_s} s")
            time.sleep(poll_s)

    def click(self, x: float, y: float) -> None:
        """A left click at (x, y) CSS pixels of the viewport."""
        for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
            params = {"type": kind, "x": x, "y": y, "button": "left", "clickCount": 1}
            if kind == "mouseMoved":
                params = {"type": kind, "x": x, "y": y}
            self.call("Input.dispatchMouseEvent", params)

    def screenshot(self, path: Path) -> Path:
        """Write a PNG of the viewport to ``path``."""
        data = self.call("Page.captureScreenshot", {"format": "png"}, timeout_s=120)["data"]
        path.write_bytes(base64.b64decode(data))
        return path

    def close(self) -> None:
        """Stop the browser (its whole process group)."""
        for fd in (getattr(self, "_w", None), getattr(self, "_r", None)):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._w = self._r = None  # type: ignore[assignment]
        proc = getattr(self, "_proc", None)
        if proc is not None and proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.wait(timeout=30)

    def __enter__(self) -> Page:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

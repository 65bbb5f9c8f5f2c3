"""gcm view: a saved run in the live meshcat viewer, checked in headless Chromium.

A live meshcat page receives its scene over a websocket after it loads, so a
plain ``--screenshot`` shows only the grid; Chromium is driven through the
DevTools protocol instead (navigate, wait for the scene, capture), with
tornado's websocket client (tornado comes with meshcat).
"""

from __future__ import annotations

import asyncio
import base64
import io
import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from browser import HEADLESS, chromium
from helpers import assert_one_line_error, run_gcm
from test_export import make_run

_SIZE = (1024, 768)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start_view(run: Path, *extra: str) -> tuple[subprocess.Popen[str], list[str]]:
    """Start ``gcm view RUN`` and read its output up to the viewer's URL."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "gcm_pipeline", "view", str(run), *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    lines: list[str] = []
    deadline = time.monotonic() + 120
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line.rstrip("\n"))
        if line.startswith("meshcat viewer: "):
            return proc, lines
    proc.kill()
    pytest.fail(f"gcm view printed no URL: {lines} {proc.stderr.read() if proc.stderr else ''}")


def _http_ok(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=3) as resp:
            return resp.status == 200
    except OSError:
        return False


async def _cdp_capture(port: int, url: str, done, timeout_s: float = 60.0) -> np.ndarray:
    """Navigate a page to ``url`` and capture screenshots until ``done(image)``."""
    from PIL import Image
    from tornado.websocket import websocket_connect

    targets: list[dict] = []
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and not targets:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=2) as r:
                targets = [t for t in json.load(r) if t.get("type") == "page"]
        except OSError:
            await asyncio.sleep(0.3)
    assert targets, "headless chromium exposed no page over the DevTools protocol"
    conn = await websocket_connect(targets[0]["webSocketDebuggerUrl"], max_message_size=1 << 27)
    ids = iter(range(1, 1 << 30))

    async def call(method: str, **params) -> dict:
        my = next(ids)
        await conn.write_message(json.dumps({"id": my, "method": method, "params": params}))
        while True:
            msg = json.loads(await conn.read_message())
            if msg.get("id") == my:
                assert "error" not in msg, msg
                return msg["result"]

    await call("Page.enable")
    await call("Page.navigate", url=url)
    img = None
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        await asyncio.sleep(2.0)  # the scene arrives over the websocket after load
        shot = await call("Page.captureScreenshot", format="png")
        png = Image.open(io.BytesIO(base64.b64decode(shot["data"]))).convert("RGB")
        img = np.asarray(png).astype(int)
        if done(img):
            break
    conn.close()
    assert img is not None
    return img


def _classes(img: np.ndarray) -> dict[str, int]:
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return {
        "robot": int(((r > 190) & (np.abs(r - g) < 12) & (np.abs(g - b) < 12)).sum()),
        "object": int(((r > g + 20) & (g > b + 40)).sum()),
        "grasps": int(((g > r + 20) & (g > b - 10) & (b < 200)).sum()),
    }


def _drawn(img: np.ndarray) -> bool:
    c = _classes(img)
    return (
        c["robot"] > 0.005 * img.shape[0] * img.shape[1] and c["object"] > 150 and c["grasps"] > 30
    )


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    return make_run(tmp_path_factory.mktemp("view"))


def test_gcm_view_draws_a_saved_run_in_chromium(run, tmp_path):
    before = (run / "grasps.csv").read_bytes()
    proc, lines = _start_view(run)
    browser = None
    try:
        url = lines[-1].split("meshcat viewer: ", 1)[1]
        assert url.startswith("http://127.0.0.1:") and _http_ok(url)
        port = _free_port()
        browser = subprocess.Popen(
            [
                chromium(),
                *HEADLESS,
                f"--user-data-dir={tmp_path / 'profile'}",
                f"--window-size={_SIZE[0]},{_SIZE[1]}",
                f"--remote-debugging-port={port}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
        img = asyncio.run(_cdp_capture(port, url, _drawn))
        c = _classes(img)
        assert _drawn(img), c  # robot meshes, the orange box, the viridis glyphs
        assert img.std() > 20.0
    finally:
        if browser is not None:
            os.killpg(browser.pid, signal.SIGKILL)
            browser.wait()
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C
        code = proc.wait(timeout=30)
    assert code == 0
    assert not _http_ok(url)  # the server went with it
    assert (run / "grasps.csv").read_bytes() == before  # nothing recomputed or rewritten


def test_gcm_view_no_wait_leaves_a_working_server(run):
    proc, lines = _start_view(run, "--no-wait")
    # not communicate(): it reads the pipe's fd and would miss what readline buffered
    assert proc.stdout is not None and proc.stderr is not None
    lines += proc.stdout.read().splitlines()
    err = proc.stderr.read()
    proc.wait(timeout=60)
    assert proc.returncode == 0, err
    url = next(ln for ln in lines if ln.startswith("meshcat viewer: ")).split(": ", 1)[1]
    pid_line = next((ln for ln in lines if "keeps running (pid " in ln), f"{lines} {err}")
    pid = int(pid_line.split("(pid ", 1)[1].split(")", 1)[0])
    try:
        assert _http_ok(url)  # the URL printed works after gcm view returned
    finally:
        os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and _http_ok(url):
        time.sleep(0.2)
    assert not _http_ok(url)


def test_gcm_view_bad_run_dir(tmp_path):
    proc = run_gcm("view", tmp_path / "nope", timeout=60)
    assert_one_line_error(proc.returncode, proc.stderr)

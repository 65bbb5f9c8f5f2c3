"""The live viewer: the scene sent to a meshcat server.

:func:`open_viewer` starts meshcat's own server on the loopback interface, or
connects to a running one after a time-bounded probe, so an absent server is
a :class:`~gcm_pipeline.errors.PublishError`, not a hang. A server started
here serves, at its viewer URL, the same page as ``scene.html`` with its side
panel (:mod:`gcm_pipeline.outputs.scene_page`), its scene arriving over the
websocket; another meshcat server serves meshcat's own page.
"""

from __future__ import annotations

import os
import selectors
import subprocess
import sys
import time
import weakref
from dataclasses import dataclass, field
from typing import Any

import umsgpack
import zmq

from gcm_pipeline.errors import PublishError
from gcm_pipeline.outputs.html import live_page_html
from gcm_pipeline.outputs.meshcat_lib import load_meshcat
from gcm_pipeline.outputs.robot_view import RobotPoser
from gcm_pipeline.outputs.scene import PublishOptions, SceneInfo, build_scene
from gcm_pipeline.outputs.scene_page import page_data, set_tour
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.table import GraspTable

__all__ = [
    "Viewer",
    "open_viewer",
    "probe_server",
]


# -- live viewer ------------------------------------------------------------------------

# Runs meshcat's server with the web server bound to the loopback interface
# (meshcat's own launcher listens on all interfaces for HTTP).
_SERVER_CODE = """
import os, sys, threading, time
import tornado.web
from meshcat.servers import zmqserver as z

_parent = int(sys.argv[1])
_detached = sys.argv[2:] == ["detach"]

def _watch_parent():
    # exit with the process that started us, even if it could not stop us
    while True:
        time.sleep(1.0)
        if os.getppid() != _parent:
            os._exit(0)

if not _detached:  # a detached server outlives its starter (stop it by its pid)
    threading.Thread(target=_watch_parent, daemon=True).start()

class _App(tornado.web.Application):
    def listen(self, port, address="127.0.0.1", **kwargs):
        return super().listen(port, address="127.0.0.1", **kwargs)

class _Page(tornado.web.RequestHandler):
    # the viewer's page: gcm's page with its panel once sent, else meshcat's own
    def initialize(self, bridge):
        self.bridge = bridge

    def get(self):
        page = self.bridge.gcm_page
        if page is None:
            with open(os.path.join(z.VIEWER_ROOT, z.VIEWER_HTML), "rb") as fh:
                page = fh.read()
        self.set_header("Content-Type", "text/html; charset=utf-8")
        self.set_header("Cache-Control", "no-store")
        self.write(page)

class _Bridge(z.ZMQWebSocketBridge):
    gcm_page = None

    def make_app(self):
        return _App([
            (r"/static/", _Page, {"bridge": self}),
            (r"/static/(.*)", z.StaticFileHandlerNoCache,
             {"path": z.VIEWER_ROOT, "default_filename": z.VIEWER_HTML}),
            (r"/", z.WebSocketHandler, {"bridge": self}),
        ])

    def handle_zmq(self, frames):
        if frames[0] == b"gcm_page" and len(frames) == 3:
            self.gcm_page = bytes(frames[2])
            self.zmq_socket.send(b"ok")
        else:
            super().handle_zmq(frames)

bridge = _Bridge(host="127.0.0.1")
print("zmq_url=" + bridge.zmq_url, flush=True)
print("web_url=" + bridge.web_url, flush=True)
sys.stdout = open(os.devnull, "w")
try:
    bridge.run()
except KeyboardInterrupt:
    pass
"""


def _request(sock: Any, frames: list[bytes], what: str, url: str, timeout_s: float) -> bytes:
    try:
        sock.send_multipart(frames)
        return bytes(sock.recv())
    except zmq.Again:
        raise PublishError(
            f"meshcat server at {url} did not answer {what!r} within {timeout_s:g} s "
            "(is `meshcat-server` running there? start one or set publish.zmq_url: null)"
        ) from None
    except zmq.ZMQError as exc:
        raise PublishError(f"meshcat server at {url}: {exc}") from exc


def _req_socket(url: str, timeout_s: float) -> Any:
    sock: Any = zmq.Context.instance().socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, max(1, int(timeout_s * 1000)))
    sock.setsockopt(zmq.SNDTIMEO, max(1, int(timeout_s * 1000)))
    try:
        sock.connect(url)
    except zmq.ZMQError as exc:
        sock.close(0)
        raise PublishError(
            f"invalid meshcat zmq_url {url!r}: {exc} (expected e.g. tcp://127.0.0.1:6000)"
        ) from exc
    return sock


def probe_server(zmq_url: str, timeout_s: float) -> str:
    """Ask a meshcat server for its web URL, giving up after ``timeout_s``.

    Args:
        zmq_url: The server's ZMQ address, e.g. ``tcp://127.0.0.1:6000``.
        timeout_s: Time bound [s].

    Returns:
        The server's web URL.

    Raises:
        PublishError: No answer within the time bound (names the URL) or a bad URL.
    """
    sock = _req_socket(zmq_url, timeout_s)
    try:
        return _request(sock, [b"url"], "url", zmq_url, timeout_s).decode("utf-8")
    finally:
        sock.close(0)


class _ZmqWindow:
    """meshcat's ZMQ window with time-bounded requests (a dead server raises, never hangs)."""

    def __init__(self, zmq_url: str, web_url: str, timeout_s: float) -> None:
        self.zmq_url = zmq_url
        self.web_url = web_url
        self.timeout_s = timeout_s
        self.n_objects = 0
        self._sock = _req_socket(zmq_url, timeout_s)

    def send(self, command: Any) -> None:
        data = command.lower()
        if data["type"] == "set_object":
            self.n_objects += 1
        frames = [
            data["type"].encode("utf-8"),
            data["path"].encode("utf-8"),
            umsgpack.packb(data),
        ]
        _request(self._sock, frames, data["type"], self.zmq_url, self.timeout_s)

    def send_page(self, html: str) -> bool:
        """Give the server the viewer's page (gcm's server serves it; others answer no)."""
        frames = [b"gcm_page", b"", html.encode("utf-8")]
        return _request(self._sock, frames, "gcm_page", self.zmq_url, self.timeout_s) == b"ok"

    def get_scene(self) -> str:
        return _request(
            self._sock, [b"get_scene"], "get_scene", self.zmq_url, self.timeout_s
        ).decode("utf-8")

    def close(self) -> None:
        self._sock.close(0)


def _start_server(
    timeout_s: float, detach: bool = False
) -> tuple[subprocess.Popen[bytes], str, str]:
    """Start meshcat's server on 127.0.0.1; return (process, zmq_url, web_url).

    A ``detach``-ed server keeps running after this process exits.
    """
    extra = ["detach"] if detach else []
    proc = subprocess.Popen(
        [sys.executable, "-u", "-c", _SERVER_CODE, str(os.getpid()), *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        stdin=subprocess.DEVNULL,
        start_new_session=True,
    )
    assert proc.stdout is not None
    urls: dict[str, str] = {}
    deadline = time.monotonic() + timeout_s
    buf = b""
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        while len(urls) < 2:
            left = deadline - time.monotonic()
            if left <= 0 or proc.poll() is not None:
                _stop(proc)
                why = "exited" if proc.poll() is not None else f"gave no URL in {timeout_s:g} s"
                raise PublishError(f"meshcat server on 127.0.0.1 {why}")
            if not sel.select(left):
                continue
            chunk = os.read(proc.stdout.fileno(), 4096)
            if not chunk:
                continue
            buf += chunk
            *lines, buf = buf.split(b"\n")
            for line in lines:
                key, _, value = line.decode("utf-8", "replace").strip().partition("=")
                if key in ("zmq_url", "web_url"):
                    urls[key] = value
    return proc, urls["zmq_url"], urls["web_url"]


def _stop(proc: subprocess.Popen[bytes] | None) -> None:
    if proc is None or proc.poll() is not None:
        if proc is not None and proc.stdout is not None:
            proc.stdout.close()
        return
    proc.terminate()
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    if proc.stdout is not None:
        proc.stdout.close()


@dataclass
class Viewer:
    """A live meshcat scene.

    Attributes:
        url: Web address to open in a browser.
        zmq_url: The server's ZMQ address.
        info: What the scene holds.
        visualizer: The ``meshcat.Visualizer`` (draw more with it if you like).
        owns_server: Whether :meth:`close` stops the server (started by
            :func:`open_viewer`).
        server_pid: Process id of the server started by :func:`open_viewer`
            (None for a server at ``publish.zmq_url``); a detached server
            keeps running after :meth:`close` until this process is stopped.
        panel: The server serves the page with the side panel at :attr:`url`
            (a server started here does; another meshcat server serves its own page).
    """

    url: str
    zmq_url: str
    info: SceneInfo
    visualizer: Any = field(repr=False)
    owns_server: bool = False
    server_pid: int | None = None
    panel: bool = False
    closed: bool = False
    _proc: subprocess.Popen[bytes] | None = field(default=None, repr=False)
    _finalizer: Any = field(default=None, repr=False)

    def close(self) -> None:
        """Disconnect, and stop the server if this viewer started it. Idempotent."""
        window = getattr(self.visualizer, "window", None)
        if isinstance(window, _ZmqWindow):
            window.close()
        if self._finalizer is not None:
            self._finalizer()
        self.closed = True

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_viewer(
    grasps: GraspTable,
    manifold: Any,
    robot: Robot | None,
    options: PublishOptions,
    *,
    detach: bool = False,
) -> Viewer:
    """Publish the scene to a live meshcat server.

    With ``options.zmq_url`` None, meshcat's server is started on
    127.0.0.1 (ZMQ and HTTP) and stopped by :meth:`Viewer.close` (unless
    ``detach``: then it keeps serving the scene after this process exits,
    until its ``server_pid`` is stopped); otherwise the server at ``zmq_url``
    is probed within ``options.connect_timeout_s`` and used.

    Args:
        grasps: The grasp table.
        manifold: The manifold or None.
        robot: The robot or None.
        options: The server (``zmq_url``, ``connect_timeout_s``) and the scene.
        detach: Leave a server started here running after :meth:`Viewer.close`.

    Returns:
        The viewer; open ``viewer.url`` in a browser, call ``viewer.close()`` when done.

    Raises:
        PublishError: The server is unreachable within the time bound (names the
            URL), cannot start, or stops answering.
    """
    timeout = float(options.connect_timeout_s)
    proc = None
    if options.zmq_url is None:
        proc, zmq_url, web_url = _start_server(max(timeout, 20.0), detach=detach)
    else:
        zmq_url = options.zmq_url
        web_url = probe_server(zmq_url, timeout)
    window = None
    try:
        # large scenes take a while to forward: allow more than the connect bound
        window = _ZmqWindow(zmq_url, web_url, max(timeout, 60.0))
        vis = load_meshcat().Visualizer(window=window)
        info = build_scene(vis, grasps, manifold, robot, options.scene)
        poser = RobotPoser(robot) if robot is not None else None
        tour: list[dict[str, Any]] = []
        if poser is not None:
            info, tour = set_tour(vis, grasps, poser, options.scene, info)
        data = page_data(grasps, robot, options.scene, info, poser=poser, tour=tour)
        panel = window.send_page(live_page_html(data))
    except BaseException:
        if window is not None:
            window.close()
        _stop(proc)
        raise
    viewer = Viewer(
        url=web_url,
        zmq_url=zmq_url,
        info=info,
        visualizer=vis,
        owns_server=proc is not None and not detach,
        server_pid=None if proc is None else proc.pid,
        panel=panel,
        _proc=proc,
    )
    if detach:
        if proc is not None and proc.stdout is not None:
            proc.stdout.close()
        return viewer
    # stops the server on close(), when the viewer is garbage-collected, or at exit
    viewer._finalizer = weakref.finalize(viewer, _stop, proc)
    return viewer

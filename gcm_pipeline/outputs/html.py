"""The scene as a self-contained HTML page, and the publish files of a run directory.

The HTML scene is recorded without a server: a recording window stands in for
meshcat's ZMQ connection, keeps the scene tree exactly as ``meshcat-server``
does, and writes the same static page that ``Visualizer.static_html()`` would
ask the server for. :func:`publish` writes ``scene.html`` and the plots into
a run directory.
"""

from __future__ import annotations

import base64
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import umsgpack

from gcm_pipeline.errors import OutputError, PublishError
from gcm_pipeline.outputs.meshcat_lib import load_meshcat
from gcm_pipeline.outputs.plots import write_plots
from gcm_pipeline.outputs.robot_view import ROT_X90, RobotPoser
from gcm_pipeline.outputs.scene import (
    PublishOptions,
    SceneInfo,
    SceneOptions,
    build_scene,
    stage_counts,
)
from gcm_pipeline.outputs.scene_page import data_script, page_assets, page_data, set_tour
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.rundir.transaction import atomic_file
from gcm_pipeline.table import GraspTable

__all__ = [
    "RecordingWindow",
    "live_page_html",
    "publish",
    "render_scene_html",
    "write_scene_html",
]


# -- recording window and static HTML ---------------------------------------------------


class RecordingWindow:
    """Stands in for meshcat's ZMQ window: keeps the scene tree like ``meshcat-server``.

    ``meshcat.Visualizer(window=RecordingWindow())`` draws without a server;
    :meth:`static_html` then builds the page that the server's ``get_scene``
    would return (same tree walk, same command encoding).
    """

    def __init__(self) -> None:
        self._trees = load_meshcat().servers.tree
        self.tree = self._trees.SceneTree()
        self.web_url = ""
        self.zmq_url = ""
        self.n_objects = 0

    def send(self, command: Any) -> None:
        """Apply one meshcat command to the scene tree, as the server would."""
        data = command.lower()
        kind = data["type"]
        path = [p for p in data["path"].split("/") if p]
        packed = umsgpack.packb(data)
        node = self._trees.find_node(self.tree, path)
        if kind == "set_object":
            node.object = packed
            node.properties = []
            self.n_objects += 1
        elif kind == "set_transform":
            node.transform = packed
        elif kind == "set_property":
            node.properties.append(packed)
        elif kind == "set_animation":
            node.animation = packed
        elif kind == "delete":
            if path:
                parent = self._trees.find_node(self.tree, path[:-1])
                parent.pop(path[-1], None)
            else:
                self.tree = self._trees.SceneTree()
        else:  # pragma: no cover - meshcat sends only the above
            raise PublishError(f"unsupported meshcat command {kind!r}")

    def get_image(self) -> None:  # pragma: no cover - no browser behind it
        """Refuse: a recording has no browser to capture an image from."""
        raise PublishError("a recorded scene has no browser to capture an image from")

    def commands(self) -> list[bytes]:
        """The msgpack-encoded commands in the order the server would replay them."""
        out: list[bytes] = []
        for node in self._trees.walk(self.tree):
            if node.object is not None:
                out.append(node.object)
            out.extend(node.properties)
            if node.transform is not None:
                out.append(node.transform)
            if node.animation is not None:
                out.append(node.animation)
        return out

    def static_html(
        self, extra_js: str = "", title: str = "gcm_pipeline scene", panel: str = ""
    ) -> str:
        """The self-contained page: meshcat's viewer script and the recorded commands.

        ``panel`` (HTML: the side panel's data, style and script) is inserted after
        the viewer; its script's ``gcm.init()`` runs once every command is applied.
        """
        js_path = Path(load_meshcat().__file__).parent / "viewer" / "dist" / "main.min.js"
        viewer_js = js_path.read_text(encoding="utf-8")
        parts = []
        for blob in self.commands():
            b64 = base64.b64encode(blob).decode("ascii")
            parts.append(
                f'gcmCommands.push(fetch("data:application/octet-binary;base64,{b64}")\n'
                "    .then(res => res.arrayBuffer())\n"
                "    .then(buffer => viewer.handle_command_bytearray(new Uint8Array(buffer))));\n"
            )
        return _HTML.format(
            title=title,
            mainminjs=viewer_js,
            commands="".join(parts),
            extra=extra_js,
            panel=panel,
        )


#: The start of both pages: meshcat's viewer pane, its script, and the panel.
_PAGE_HEAD = """<!DOCTYPE html>
<html>
    <head> <meta charset=utf-8> <title>{title}</title> </head>
    <body>
        <div id="meshcat-pane">
        </div>
        <script>
{mainminjs}
        </script>
        <style>
            body {{margin: 0; }}
            #meshcat-pane {{
                width: 100vw;
                height: 100vh;
                overflow: hidden;
            }}
        </style>
{panel}
"""

_HTML = (
    _PAGE_HEAD
    + """        <script>
            var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
            var gcmCommands = [];
{commands}
{extra}
            Promise.all(gcmCommands).then(() => {{
                if (window.gcm) {{ window.gcm.init(); }}
            }});
        </script>
        <script id="embedded-json"></script>
    </body>
</html>
"""
)


_LIVE_HTML = (
    _PAGE_HEAD
    + """        <script>
            var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
            viewer.connect();
            (function wait(t0) {{
                if (window.gcm && (gcm.arrived() || performance.now() - t0 > {wait_ms})) {{
                    gcm.init();
                }} else {{
                    setTimeout(function () {{ wait(t0); }}, 200);
                }}
            }})(performance.now());
        </script>
    </body>
</html>
"""
)
#: The live page waits this long for the scene before it builds its panel anyway [ms].
_LIVE_WAIT_MS = 30000


def _panel_html(data: dict[str, Any]) -> str:
    js, css = page_assets()
    return f"<style>\n{css}</style>\n{data_script(data)}\n<script>\n{js}</script>"


def live_page_html(data: dict[str, Any], title: str = "gcm_pipeline scene (live)") -> str:
    """The live viewer's page: meshcat's viewer fed over its server's websocket, and the panel.

    Args:
        data: The panel's data (:func:`~gcm_pipeline.outputs.scene_page.page_data`).
        title: The page's title.
    """
    js_path = Path(load_meshcat().__file__).parent / "viewer" / "dist" / "main.min.js"
    return _LIVE_HTML.format(
        title=title,
        mainminjs=js_path.read_text(encoding="utf-8"),
        panel=_panel_html(data),
        wait_ms=_LIVE_WAIT_MS,
    )


def _orbit_js(target: Sequence[float]) -> str:
    """Script that turns the page's orbit controls about ``target`` (world, [m])."""
    x, y, z = (float(v) for v in ROT_X90.T @ np.asarray(target, dtype=float))
    return (
        f"viewer.controls.target.set({x!r}, {y!r}, {z!r});\n"
        "viewer.controls.update();\nviewer.set_dirty();\n"
    )


def render_scene_html(
    grasps: GraspTable, manifold: Any, robot: Robot | None, options: SceneOptions
) -> tuple[str, SceneInfo]:
    """Build the scene without a server and return the self-contained HTML page.

    The scene (:func:`~gcm_pipeline.outputs.scene.build_scene`), its top-k tour
    (:func:`~gcm_pipeline.outputs.scene_page.set_tour`) and the side panel
    around the viewer (:mod:`gcm_pipeline.outputs.scene_page`).

    Args:
        grasps: The grasp table.
        manifold: The manifold or None.
        robot: The robot or None.
        options: The scene's options.

    Returns:
        The page (opens from disk, no server) and what it holds.
    """
    window = RecordingWindow()
    vis = load_meshcat().Visualizer(window=window)
    info = build_scene(vis, grasps, manifold, robot, options, orbit_target=True)
    poser = None
    tour: list[dict[str, Any]] = []
    if robot is not None:
        poser = RobotPoser(robot)
        info, tour = set_tour(vis, grasps, poser, options, info)
    data = page_data(grasps, robot, options, info, poser=poser, tour=tour)
    panel = _panel_html(data)
    html = window.static_html(extra_js=_orbit_js(info.camera["target"]), panel=panel)
    return html, info


def write_scene_html(
    path: str | os.PathLike[str],
    grasps: GraspTable,
    manifold: Any,
    robot: Robot | None,
    options: SceneOptions,
) -> SceneInfo:
    """Write the self-contained HTML scene to ``path`` (see :func:`render_scene_html`).

    The page is written to a temporary sibling and renamed: a full disk or
    Ctrl-C leaves the old file (or none), never half a page. A symbolic link
    is written through.
    """
    html, info = render_scene_html(grasps, manifold, robot, options)
    path = Path(path)
    if path.is_symlink():
        path = path.resolve()
    if path.exists() and not path.is_file():  # a directory, /dev/null: a rename would replace it
        raise PublishError(f"cannot write scene {str(path)!r}: it is not a regular file")
    try:
        with atomic_file(path) as tmp:
            tmp.write_text(html, encoding="utf-8")
    except OutputError as exc:
        raise PublishError(str(exc)) from exc
    except OSError as exc:
        raise PublishError(f"cannot write scene {str(path)!r}: {exc}") from exc
    return info


def publish(
    grasps: GraspTable,
    manifold: Any,
    robot: Robot | None,
    options: PublishOptions,
    out_dir: str | os.PathLike[str],
    counts: Mapping[str, int] | None = None,
) -> list[Path]:
    """Write the files ``options`` asks for into ``out_dir``.

    ``scene.html`` (when ``options.html``) and ``manifold.png``,
    ``manipulability_hist.png``, ``counts.png`` (when ``options.plots``). The
    live viewer is separate (:func:`~gcm_pipeline.outputs.live.open_viewer`), called once the run
    directory is complete.

    Args:
        grasps: The grasp table.
        manifold: The manifold or None.
        robot: The robot or None.
        options: What to publish, and the scene's options.
        out_dir: An existing directory.
        counts: Per-stage counts for the bar chart (default: :func:`stage_counts`).

    Returns:
        The paths written, in that order.

    Raises:
        PublishError: A file cannot be written.
    """
    out = Path(out_dir)
    written: list[Path] = []
    if options.html:
        path = out / "scene.html"
        write_scene_html(path, grasps, manifold, robot, options.scene)
        written.append(path)
    if options.plots:
        counts = counts or stage_counts(grasps, manifold)
        written += write_plots(grasps, manifold, counts, out, base_pose=options.scene.base_pose)
    return written

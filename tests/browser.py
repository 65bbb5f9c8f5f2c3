"""Debian's Chromium for the browser tests: from PATH, else installed, else skip or fail.

The browser is Debian's ``chromium``: taken from PATH, else installed with
``apt-get`` when the tests run as root on a machine that has it. Where it
cannot be had the test is skipped with a one-line reason, except under CI:
``.ci/run`` sets ``GCM_REQUIRE_BROWSER=1``, which makes a missing browser a
failure.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

__all__ = ["HEADLESS", "chromium"]

#: Flags of every headless Chromium the tests start: software GL (no GPU here), and no
#: background connections (this machine's closed network refuses them, many at a time).
HEADLESS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)


_INSTALL: dict[str, str | None] = {}


def _install_chromium() -> str | None:
    """Install Debian's chromium with apt-get (once per session); None, or why not."""
    if "result" in _INSTALL:
        return _INSTALL["result"]
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        why: str | None = "not root, so not installed; apt-get install chromium"
    elif shutil.which("apt-get") is None:
        why = "no apt-get here to install it"
    else:
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        why = None
        for cmd in (["apt-get", "update", "-qq"], ["apt-get", "install", "-y", "-qq", "chromium"]):
            try:
                done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
            except (OSError, subprocess.TimeoutExpired) as exc:
                why = f"{' '.join(cmd)} failed: {exc}"
                break
            if done.returncode != 0:
                last = (done.stderr.strip().splitlines() or ["?"])[-1]
                why = f"{' '.join(cmd)} failed: {last}"
                break
    _INSTALL["result"] = why
    return why


def chromium() -> str:
    """Debian's chromium: from PATH, else installed (root + apt-get), else skip or fail."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is not None:
        return exe
    why = _install_chromium()
    if why is None:
        installed = Path("/usr/bin/chromium")
        exe = shutil.which("chromium") or (str(installed) if installed.is_file() else None)
        if exe is not None:
            return exe
        why = "apt-get installed chromium but there is no /usr/bin/chromium"
    message = f"chromium not found on PATH ({why})"
    if os.environ.get("GCM_REQUIRE_BROWSER") == "1":
        pytest.fail(f"{message}; GCM_REQUIRE_BROWSER=1 (.ci/run) requires the browser test")
    pytest.skip(f"{message}; browser test skipped")

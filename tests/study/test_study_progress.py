"""gcm study off a terminal: Ray's start-up said as such, then a progress line every few s.

A real study on Ray started on this machine, in a subprocess whose stderr is a
pipe (no terminal), read line by line as it comes.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tempfile
import time

import yaml
from helpers import BOTTLE, gcm_env
from helpers import SMALL_STUDY as SMALL

PROGRESS = re.compile(r"study: (\d+)/(\d+) placements, ")


def test_progress_lines_come_while_the_study_runs_and_ray_start_up_is_reported(tmp_path):
    xs = [0.30, 0.35, 0.40, 0.45, 0.50, 0.55]
    data = {
        "base": str(BOTTLE),
        "set": SMALL,
        "sweep": {"object_pose": {"x": xs, "yaw_deg": [0, 20]}},
    }
    study = tmp_path / "study.yaml"
    study.write_text(yaml.safe_dump(data, sort_keys=False))
    out = tmp_path / "out"
    ray_tmp = tempfile.mkdtemp(prefix="gcm-ray-", dir="/tmp")  # short: Ray's socket paths
    env = gcm_env(RAY_TMPDIR=ray_tmp, GCM_PROGRESS_INTERVAL_S="0.3")
    argv = [sys.executable, "-m", "gcm_pipeline", "study", str(study), "--out", str(out)]
    seen: list[tuple[float, str, bool]] = []  # (time, line, the study was still running)
    try:
        with open(tmp_path / "stdout.txt", "w") as stdout:
            proc = subprocess.Popen(
                [*argv, "--workers", "1"], stdout=stdout, stderr=subprocess.PIPE, text=True, env=env
            )
            assert proc.stderr is not None
            for line in proc.stderr:  # as it comes
                seen.append((time.perf_counter(), line.rstrip("\n"), proc.poll() is None))
            proc.wait(timeout=300)
    finally:
        shutil.rmtree(ray_tmp, ignore_errors=True)
    text = [line for _, line, _ in seen]
    assert proc.returncode == 0, "\n".join(text)
    assert "Traceback" not in "\n".join(text)
    # Ray's start-up, said as such, before any placement line
    start = text.index("study: starting Ray (1 worker)...")
    ready = next(i for i, t in enumerate(text) if t.startswith("study: Ray ready in "))
    assert re.fullmatch(r"study: Ray ready in [\d.]+ s \(1 worker on 1 node\)", text[ready])
    progress = [(i, t, running) for i, (_, t, running) in enumerate(seen) if PROGRESS.match(t)]
    assert start < ready < progress[0][0]
    # progress lines came while the study still ran, some in the middle of the placements
    assert all(running for _, _, running in progress[:-1])
    counts = [int(PROGRESS.match(t).group(1)) for _, t, _ in progress]
    assert all(PROGRESS.match(t).group(2) == "12" for _, t, _ in progress)
    assert any(0 < k < 12 for k in counts), text
    assert counts == sorted(counts)
    mid = next(t for _, t, _ in progress if 0 < int(PROGRESS.match(t).group(1)) < 12)
    assert re.fullmatch(
        r"study: \d+/12 placements, [\d.,]+ placements/s, eta \d+ s, best [\d.]+ \(#\d+\)", mid
    )
    # the last: all done, then best/ is written and the summary printed on stdout
    assert re.fullmatch(
        r"study: 12/12 placements, [\d.,]+ placements/s, in [\d.]+ s.*", text[progress[-1][0]]
    )
    assert any(t.startswith("study: writing best/, the run of placement #") for t in text)
    printed = (tmp_path / "stdout.txt").read_text()
    assert "best placement #" in printed

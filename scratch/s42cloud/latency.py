"""Signal latency of `gcm run` on the cloud scene: signal at a delay, time to exit, leftovers.

    cd TREE && PYTHONPATH=TREE python scratch/s42cloud/latency.py CLOUD.npy OUT.json DELAY ...

For each delay [s] after the start and each of SIGTERM and SIGINT: `gcm run -v` into a
fresh parent directory, the signal sent at the delay, the wall time from the signal to its
"interrupted" line and to the process's exit, its exit code, the main thread's innermost
frames (faulthandler's dump on SIGUSR1 just before: where the signal landed), the last
stage logged, and what is left in the parent directory (nothing: the run did not finish).
"""

import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

cloud, out = sys.argv[1], sys.argv[2]
delays = [float(d) for d in sys.argv[3:]]
cfg = Path(__file__).resolve().parent / "cloud_scene.yaml"
rows = []


def _read(stream, lines):
    """Each line of ``stream`` with the time it came, into ``lines``."""
    for ln in stream:
        lines.append((time.perf_counter(), ln))


# `python -m gcm_pipeline` with faulthandler's stack dump on SIGUSR1 (written at once, even
# while C code runs)
WRAP = (
    "import faulthandler, runpy, signal, sys; faulthandler.register(signal.SIGUSR1); "
    "sys.argv[0] = 'gcm'; runpy.run_module('gcm_pipeline', run_name='__main__')"
)
for delay in delays:
    for sig in (signal.SIGTERM, signal.SIGINT):
        parent = Path(tempfile.mkdtemp(prefix="lat_", dir="/tmp/s42c"))
        cmd = [
            sys.executable,
            "-c",
            WRAP,
            "run",
            str(cfg),
            "--set",
            f"environment.point_clouds.0.path={cloud}",
            "--out",
            str(parent / "run"),
            "-v",
        ]
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        lines = []
        reader = threading.Thread(target=_read, args=(p.stderr, lines))
        reader.start()
        time.sleep(delay)
        if p.poll() is not None:
            rows.append({"delay": delay, "signal": sig.name, "finished_before": True})
            continue
        p.send_signal(signal.SIGUSR1)  # faulthandler: where the main thread is now
        t0 = time.perf_counter()
        p.send_signal(sig)
        rc = p.wait()
        lat = time.perf_counter() - t0
        reader.join()
        text = "".join(ln for _, ln in lines)
        said = next((t - t0 for t, ln in lines if ln.startswith("interrupted")), None)
        # the main thread's stack: the block that is not the progress line's thread
        blocks = re.split(
            r"(?:Current thread|Thread) 0x[0-9a-f]+ \(most recent call first\):", text
        )
        dump = next(
            (b for b in blocks[1:] if "progress.py" not in b and "threading.py" not in b), ""
        )
        frames = re.findall(
            r'File "[^"]*/((?:gcm_pipeline|site-packages)/[^"]+)", line (\d+) in (\S+)', dump
        )
        stages = re.findall(r"stage (\w+) +[0-9.]+ s", text)
        rows.append(
            {
                "delay": delay,
                "signal": sig.name,
                "latency_s": round(lat, 3),
                "to_message_s": None if said is None else round(said, 3),
                "exit": rc,
                "where": [f"{f}:{n} {fn}" for f, n, fn in frames[:3]],
                "after_stage": stages[-1] if stages else None,
                "left": sorted(os.listdir(parent)),
            }
        )
        print(json.dumps(rows[-1]), flush=True)
json.dump(rows, open(out, "w"), indent=1)

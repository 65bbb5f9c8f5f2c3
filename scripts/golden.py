"""Golden outputs: prove that a refactor leaves every user-visible output unchanged.

``record OUTDIR`` runs the ``gcm`` CLI (in subprocesses, with the code of this
checkout on PYTHONPATH) on every ``configs/*.yaml``, the placement study
``configs/studies/bottle_placement.yaml``, two queries and every export format
on the bottle run, then writes ``OUTDIR/golden.json``: the sha256 of every
produced file after normalisation, plus the git commit the outputs came from.

``check OUTDIR`` re-runs the same commands into a temporary directory and
compares them with ``OUTDIR/golden.json``; it prints each file that differs
(with a short unified diff of the normalised text when the recorded file is
still in OUTDIR) and exits 1, or prints ``golden: N files identical`` and
exits 0.

Normalisation removes only what varies from run to run or from checkout to
checkout (found by recording twice and diffing); everything else is compared
byte for byte:

* absolute paths: the repository root and the output directory are replaced
  by ``<REPO>`` and ``<OUT>`` in every text file (config.yaml and summary.json
  hold the config's ``output.dir``, the study files the spec's path and the
  placement commands);
* JSON keys in ``VOLATILE_JSON`` (timings, dates, random ids, the package's own
  version, Ray node ids, the study's start-up time); those files are compared
  as parsed JSON re-serialised, so a pure whitespace change in them is not seen;
* the columns ``time_s`` and ``node`` of ``placements.csv`` and the same keys in
  the JSON ``row`` stored in each ``placements/*.npz`` (compared array by array:
  name, dtype, shape, bytes);
* the PID in the study's ``.study.lock``;
* ``scene.html``: meshcat's static HTML embeds its scene commands as base64
  msgpack whose geometry/material/object ``uuid`` fields come from
  ``uuid.uuid1()`` (time and host based); each uuid is replaced by a counter in
  order of first appearance (same length, so the msgpack stays valid).

PNG (matplotlib writes no date in PNG metadata), NPZ (numpy writes fixed zip
dates), Parquet, CSV, YAML exports and query answers are deterministic and are
hashed as written.
"""

from __future__ import annotations

import argparse
import base64
import csv
import difflib
import hashlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
STUDY = "configs/studies/bottle_placement.yaml"
QUERY_RUN = "bottle_side"
# A side grasp of the bottle near its best-ranked one (x y z qw qx qy qz, world).
QUERY_POSE = ["0.5", "0.0", "0.15", "0.5", "0.5", "-0.5", "0.5"]
EXPORTS = {"moveit": "yaml", "parquet": "parquet", "npz": "npz"}

# Volatile JSON keys, as dotted paths, per file (glob on the path below OUTDIR).
VOLATILE_JSON: dict[str, list[str]] = {
    # run/study marker: a random id, its creation date, the package version
    "**/.gcm.json": ["id", "created", "version"],
    # a run's summary: wall-clock time per stage, the package version
    "runs/*/summary.json": ["timings_s", "versions.gcm_pipeline"],
    "study/best/summary.json": ["timings_s", "versions.gcm_pipeline"],
    # the study's resume key file: creation time (epoch seconds), and the key itself: it
    # hashes the spec's absolute base directory, so it differs between checkouts (the
    # spec it is derived from is compared, paths normalised)
    "study/study.json": ["created", "key"],
    # the study summary: Ray node ids, times, throughput, package version
    "study/summary.json": [
        "best.node",
        "best.time_s",
        "engine.worker_nodes",
        "engine.startup_s",
        "timings_s",
        "placements_per_s",
        "versions.gcm_pipeline",
        "study.key",  # a hash of the absolute base directory (see study.json)
    ],
}
# Per-placement volatile fields (placements.csv columns, placements/*.npz row JSON).
VOLATILE_PLACEMENT = ["time_s", "node"]

UUID = re.compile(rb"[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}")
DATA_URL = re.compile(rb"(data:application/octet-binary;base64,)([A-Za-z0-9+/=]+)")


def commands(out: Path) -> list[tuple[str, list[str], Path | None]]:
    """The recorded commands: (label, gcm arguments, file for stdout or None)."""
    cmds: list[tuple[str, list[str], Path | None]] = []
    for cfg in sorted((REPO / "configs").glob("*.yaml")):
        args = ["run", f"configs/{cfg.name}", "--out", str(out / "runs" / cfg.stem), "--force"]
        cmds.append((f"run {cfg.name}", args, None))
    # --workers 2: the study records its worker count; pin it across machines.
    args = ["study", STUDY, "--out", str(out / "study"), "--workers", "2"]
    cmds.append(("study bottle_placement", args, None))
    run = str(out / "runs" / QUERY_RUN)
    cmds.append(
        (
            "query --json",
            ["query", run, "--pose", *QUERY_POSE, "--json"],
            out / "query" / "query.json",
        )
    )
    cmds.append(("query", ["query", run, "--pose", *QUERY_POSE], out / "query" / "query.txt"))
    for fmt, ext in EXPORTS.items():
        args = ["export", run, "--format", fmt, "--out", str(out / "export" / f"{QUERY_RUN}.{ext}")]
        cmds.append((f"export {fmt}", args, None))
    return cmds


def run_all(out: Path) -> float:
    """Run every command into ``out`` (owned subdirectories cleared first); seconds taken."""
    for sub in ("runs", "study", "query", "export"):
        shutil.rmtree(out / sub, ignore_errors=True)  # a study directory would resume
    (out / "query").mkdir(parents=True)
    (out / "export").mkdir(parents=True)
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    gcm = [sys.executable, "-m", "gcm_pipeline"]  # the `gcm` entry point
    start = time.perf_counter()
    for label, args, stdout in commands(out):
        t0 = time.perf_counter()
        print(f"golden: {label} ...", end="", flush=True)
        proc = subprocess.run(
            [*gcm, *args, "--quiet"], cwd=REPO, env=env, capture_output=True, text=True
        )
        if proc.returncode != 0:
            print(f" failed (exit {proc.returncode})\n{proc.stderr}", file=sys.stderr)
            raise SystemExit(2)
        if stdout is not None:
            stdout.write_text(proc.stdout)
        print(f" {time.perf_counter() - t0:.1f} s", flush=True)
    return time.perf_counter() - start


def _drop(obj: dict, dotted: str) -> None:
    *parents, last = dotted.split(".")
    for key in parents:
        obj = obj.get(key) if isinstance(obj, dict) else None
        if obj is None:
            return
    if isinstance(obj, dict):
        obj.pop(last, None)


def _paths(text: str, out: Path) -> str:
    # the output directory first: it may lie inside the repository
    return text.replace(str(out), "<OUT>").replace(str(REPO), "<REPO>")


def _normalise_npz(data: bytes) -> bytes:
    """Placement npz: arrays in order, with the volatile keys of the JSON ``row`` removed."""
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        parts = []
        for name in zf.namelist():
            arr = np.load(io.BytesIO(zf.read(name)), allow_pickle=False)
            if name == "row.npy" and arr.dtype.kind == "U" and arr.ndim == 0:
                row = json.loads(str(arr))
                for key in VOLATILE_PLACEMENT:
                    row.pop(key, None)
                arr = np.array(json.dumps(row))
            header = f"{name} {arr.dtype.str} {arr.shape}\n".encode()
            parts.append(header + np.ascontiguousarray(arr).tobytes())
    return b"".join(parts)


def _normalise_csv(text: str) -> str:
    rows = list(csv.reader(io.StringIO(text)))
    drop = [i for i, name in enumerate(rows[0]) if name in VOLATILE_PLACEMENT] if rows else []
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    for n, row in enumerate(rows):
        writer.writerow(["" if n and i in drop else v for i, v in enumerate(row)])
    return buf.getvalue()


def _normalise_html(data: bytes) -> bytes:
    ids: dict[bytes, bytes] = {}

    def uuid(m: re.Match) -> bytes:
        return ids.setdefault(m.group(0), b"%08d-0000-0000-0000-000000000000" % len(ids))

    def payload(m: re.Match) -> bytes:
        raw = base64.b64decode(m.group(2))
        return m.group(1) + base64.b64encode(UUID.sub(uuid, raw))

    return DATA_URL.sub(payload, data)


def normalise(rel: str, data: bytes, out: Path) -> bytes:
    """The bytes of the file ``rel`` (below ``out``) that must not change."""
    p = Path(rel)
    if p.name == "scene.html":
        return _normalise_html(data)
    if p.suffix == ".npz" and rel.startswith("study/placements/"):
        return _normalise_npz(data)
    if p.name == ".study.lock":
        return re.sub(rb"\d+", b"<PID>", data)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        return data  # binary: PNG, NPZ, Parquet
    text = _paths(text, out)
    if rel == "study/placements.csv":
        text = _normalise_csv(text)
    keys = [
        k for pattern, ks in VOLATILE_JSON.items() if p.match(pattern) or rel == pattern for k in ks
    ]
    if keys:
        obj = json.loads(text)
        for key in keys:
            _drop(obj, key)
        text = json.dumps(obj, indent=1, ensure_ascii=False) + "\n"
    return text.encode("utf-8")


def digest(out: Path) -> dict[str, str]:
    """sha256 of every normalised file below ``out`` (relative POSIX path -> hex)."""
    files = sorted(f for f in out.rglob("*") if f.is_file() and f.name != "golden.json")
    return {
        f.relative_to(out).as_posix(): hashlib.sha256(
            normalise(f.relative_to(out).as_posix(), f.read_bytes(), out)
        ).hexdigest()
        for f in files
    }


def git_commit() -> dict[str, object]:
    """The commit of this checkout and whether tracked files differ from it."""

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", *args], cwd=REPO, capture_output=True, text=True, check=True
        ).stdout.strip()

    return {
        "commit": git("rev-parse", "HEAD"),
        "dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
    }


def record(out: Path) -> int:
    """Run every command into ``out`` and write ``out/golden.json``."""
    out.mkdir(parents=True, exist_ok=True)
    commit = git_commit()  # the code that runs, before anything else is committed
    seconds = run_all(out.resolve())
    files = digest(out.resolve())
    golden = {**commit, "files": files}
    (out / "golden.json").write_text(json.dumps(golden, indent=1) + "\n")
    print(f"golden: recorded {len(files)} files in {seconds:.0f} s -> {out / 'golden.json'}")
    return 0


def _diff(old: bytes, new: bytes, rel: str, width: int = 160, lines: int = 20) -> str:
    try:
        a, b = old.decode("utf-8").splitlines(), new.decode("utf-8").splitlines()
    except UnicodeDecodeError:
        return ""
    diff = difflib.unified_diff(a, b, f"golden/{rel}", f"now/{rel}", n=1, lineterm="")
    cut = [line if len(line) <= width else line[:width] + " ..." for line in diff]
    more = f"\n  ... {len(cut) - lines} more diff lines" if len(cut) > lines else ""
    return "\n".join("  " + line for line in cut[:lines]) + more


def check(out: Path) -> int:
    """Re-run every command into a temporary directory and compare with ``out/golden.json``."""
    out = out.resolve()
    golden = json.loads((out / "golden.json").read_text())
    with tempfile.TemporaryDirectory(prefix="gcm-golden-") as tmp:
        now_dir = Path(tmp)
        seconds = run_all(now_dir)
        now = digest(now_dir)
        bad = 0
        for rel in sorted(set(golden["files"]) | set(now)):
            want, got = golden["files"].get(rel), now.get(rel)
            if want == got:
                continue
            bad += 1
            if got is None:
                print(f"golden: MISSING {rel}")
            elif want is None:
                print(f"golden: NEW {rel}")
            else:
                print(f"golden: DIFFERS {rel}")
                old_file = out / rel
                if old_file.is_file():
                    old = normalise(rel, old_file.read_bytes(), out)
                    if hashlib.sha256(old).hexdigest() != want:
                        print(f"  ({old_file} changed since it was recorded: diff against it)")
                    new = normalise(rel, (now_dir / rel).read_bytes(), now_dir)
                    text = _diff(old, new, rel)
                    if text:
                        print(text)
    print(f"golden: commands took {seconds:.0f} s; recorded at {golden['commit'][:12]}")
    if bad:
        print(f"golden: {bad} of {len(golden['files'])} files differ")
        return 1
    print(f"golden: {len(now)} files identical")
    return 0


def main() -> int:
    """Command line: ``record OUTDIR`` or ``check OUTDIR``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=["record", "check"])
    parser.add_argument("outdir", type=Path)
    args = parser.parse_args()
    return record(args.outdir) if args.command == "record" else check(args.outdir)


if __name__ == "__main__":
    sys.exit(main())

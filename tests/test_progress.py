"""The one progress helper: a bar on a terminal, log lines (or nothing) elsewhere."""

from __future__ import annotations

import io
import re
import sys

from gcm_pipeline import progress


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_reporter_off_a_terminal_writes_lines_with_rate_and_eta(monkeypatch, capsys):
    monkeypatch.setattr(progress, "PROGRESS_INTERVAL_S", 0.0)
    with progress.Reporter(1000, desc="reachability", unit="pose") as report:
        assert report.bar is None  # capsys' stderr is no terminal
        report(250)
        report(750)  # the last chunk: no line until close
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2
    assert re.fullmatch(
        r"reachability: 250/1,000 poses \(25 %\), [\d,]+ poses/s, ETA \d+ s", lines[0]
    )
    assert re.fullmatch(
        r"reachability: 1,000/1,000 poses \(100 %\), [\d,]+ poses/s in [\d.]+ s", lines[1]
    )


def test_reporter_writes_nothing_when_disabled_or_quick(capsys):
    with progress.Reporter(10, enabled=False, desc="x") as report:
        report(10)
    with progress.Reporter(10, desc="x") as report:  # done before the first interval
        report(10)
    with progress.Reporter(0, desc="x") as report:
        report(0)
    assert capsys.readouterr().err == ""


def test_reporter_on_a_terminal_draws_a_bar(monkeypatch):
    term = _Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    with progress.Reporter(100, desc="reachability", unit="pose") as report:
        assert report.bar is not None
        report(40)
    out = term.getvalue()
    assert "reachability:" in out and "/100 " in out and "pose/s" in out  # unit_scale, rate


def test_bar_is_silent_off_a_terminal_and_when_disabled(monkeypatch, capsys):
    b = progress.bar(3, "gcm", "stage", leave=False)
    b.set_postfix_str("ik")
    b.update(3)
    b.close()
    assert b.disable and capsys.readouterr().err == ""
    term = _Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    off = progress.bar(3, "gcm", "stage", enabled=False)
    off.update(1)
    off.close()
    assert off.disable and term.getvalue() == ""
    on = progress.bar(3, "study", "placement", initial=1)
    on.update(1)
    on.close()
    assert "study" in term.getvalue() and "2/3" in term.getvalue()


def test_line_bar_off_a_terminal_prints_lines_while_nothing_finishes(monkeypatch, capsys):
    """A study's placements: lines from a thread every interval, with rate, eta and postfix."""
    import time

    monkeypatch.setenv(progress.INTERVAL_ENV, "0.05")
    b = progress.bar(48, "study", "placement", lines=True, initial=2)
    assert isinstance(b, progress.LineBar)
    time.sleep(0.2)  # nothing finished: lines all the same
    b.update(10)
    b.set_postfix_str("best 0.806 (#7)")
    time.sleep(0.2)
    b.close()
    b.close()  # once only
    lines = capsys.readouterr().err.splitlines()
    assert re.fullmatch(r"study: 2/48 placements, none finished yet \(\d+ s\)", lines[0])
    later = [ln for ln in lines if ln.startswith("study: 12/48")]
    assert later and re.fullmatch(
        r"study: 12/48 placements, [\d.,]+ placements/s, eta \d+ s, best 0\.806 \(#7\)",
        later[0],
    )
    assert lines[-1] == later[-1] and len(lines) >= 4


def test_line_bar_says_nothing_when_closed_before_its_first_line(monkeypatch, capsys):
    monkeypatch.setenv(progress.INTERVAL_ENV, "60")
    b = progress.bar(3, "study", "placement", lines=True)
    b.update(3)
    b.close()
    assert capsys.readouterr().err == ""


def test_the_interval_comes_from_the_environment_when_it_is_a_positive_number(monkeypatch):
    for value, want in (("2.5", 2.5), ("0", 5.0), ("-1", 5.0), ("nan", 5.0), ("x", 5.0)):
        monkeypatch.setenv(progress.INTERVAL_ENV, value)
        assert progress.interval() == want
    monkeypatch.delenv(progress.INTERVAL_ENV)
    assert progress.interval() == progress.PROGRESS_INTERVAL_S


def test_on_a_terminal_or_disabled_a_line_bar_is_never_made(monkeypatch, capsys):
    off = progress.bar(3, "study", "placement", lines=True, enabled=False)
    assert not isinstance(off, progress.LineBar) and off.disable
    term = _Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    on = progress.bar(3, "study", "placement", lines=True)
    assert not isinstance(on, progress.LineBar)
    on.update(1)
    on.close()
    assert "1/3" in term.getvalue()


def test_stage_lines_name_a_long_stage_only(monkeypatch, capsys):
    """``gcm run`` off a terminal: a line for a stage running longer than the interval."""
    import time

    monkeypatch.setenv(progress.INTERVAL_ENV, "0.1")
    b = progress.bar(9, "gcm", "stage", lines=True, stages=True, leave=False)
    assert isinstance(b, progress.LineBar)
    for name in ("candidates", "manifold", "densify"):  # short stages: nothing
        b.set_postfix_str(name)
        time.sleep(0.02)
        b.update(1)
    b.set_postfix_str("publish")
    time.sleep(0.45)
    b.update(1)
    b.close()
    lines = capsys.readouterr().err.splitlines()
    assert lines, "a long stage prints lines"
    for line in lines:
        assert re.fullmatch(r"gcm: stage 4/9 \(publish\) for \d+ s", line) or re.fullmatch(
            r"gcm: stage 5/9 \(publish\) for \d+ s", line
        ), line


def test_stage_lines_keep_quiet_while_another_progress_line_comes(monkeypatch, capsys):
    """The reachability stage prints its own lines: the stage line does not repeat them."""
    import time

    monkeypatch.setenv(progress.INTERVAL_ENV, "0.1")
    b = progress.bar(9, "gcm", "stage", lines=True, stages=True)
    b.set_postfix_str("reachability")
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < 0.5:
        progress._say("reachability: ...")
        time.sleep(0.03)
    b.close()
    assert set(capsys.readouterr().err.splitlines()) == {"reachability: ..."}


def test_gcm_run_off_a_terminal_names_its_long_stages(tmp_path):
    """A real ``gcm run`` with stderr piped: publishing the scene and plots takes seconds."""
    from helpers import BOTTLE, run_gcm

    proc = run_gcm(
        "run", BOTTLE, "--out", tmp_path / "run", env={progress.INTERVAL_ENV: "0.5"}, timeout=600
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stderr.splitlines()
    stage = [ln for ln in lines if ln.startswith("gcm: stage ")]
    assert stage and all(
        re.fullmatch(r"gcm: stage \d/\d \([a-z_]+\) for \d+ s", ln) for ln in stage
    ), lines
    assert any("(publish)" in ln for ln in stage), lines
    assert re.fullmatch(r"gcm: (\d)/\1 stages in [\d.]+ s", lines[-1]), lines

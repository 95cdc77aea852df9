"""Ctrl-C during each stage of ``dhptam run``, and panics at the Python boundary (issue 10).

A Ctrl-C raised in the reader thread, the front-end thread, the extraction thread (``test_run.py``), on the
tracking thread, while the back-end stops, or while the outputs are written stops the run
cleanly: ``interrupted`` is set and every output holds the frames done so far. A real SIGINT
to the ``dhptam run`` process exits with 130 and no traceback.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

import dhptam.frontend
import dhptam.system
import dhptam.trajectory
from dhptam.errors import DhptamError, InternalError
from dhptam.run import run
from dhptam.trajectory import read_tum

OUTPUTS = (
    "trajectory.tum",
    "trajectory_frame_left.tum",
    "keyframes.tum",
    "map.ply",
    "frames.csv",
    "timing.json",
)


def _interrupt_on_call(monkeypatch: pytest.MonkeyPatch, owner: Any, name: str, at: int) -> None:
    """``owner.name`` raises KeyboardInterrupt on call number ``at`` (after doing its work when
    ``after`` is set), as a Ctrl-C arriving during that call does."""
    original = getattr(owner, name)
    calls = {"n": 0}

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == at:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, name, wrapper)


def _check_outputs(out: Path, frames: int) -> None:
    for name in OUTPUTS:
        assert (out / name).is_file(), name
    assert len(read_tum(out / "trajectory.tum")[0]) == frames
    assert len((out / "frames.csv").read_text().splitlines()) == 1 + frames
    timing = json.loads((out / "timing.json").read_text())
    assert timing["interrupted"] is True and timing["frames"] == frames
    assert not list(out.glob(".*tmp*")), "temporary files left behind"


@pytest.mark.parametrize(
    ("stage", "method", "mode", "at"),
    [("front-end", "prepare", "frames", 9), ("reader", "read", "fusion", 7)],
)
def test_ctrl_c_in_the_frontend_and_reader_threads(
    stage: str,
    method: str,
    mode: str,
    at: int,
    sim_desk_run: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Call `at` is frame `at` − 1 on that stage's thread: the frames before it are kept.
    _interrupt_on_call(monkeypatch, dhptam.frontend.Frontend, method, at)
    result = run(sim_desk_run, tmp_path, mode=mode, progress=False)
    assert result.interrupted, stage
    _check_outputs(tmp_path, at - 1)


def test_ctrl_c_on_the_tracking_thread(
    sim_desk_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _interrupt_on_call(monkeypatch, dhptam.system.System, "track", 7)
    result = run(sim_desk_run, tmp_path, mode="frames", progress=False)
    assert result.interrupted
    _check_outputs(tmp_path, 6)


def test_ctrl_c_while_the_backend_stops(
    sim_desk_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The interrupt lands in ``System.shutdown`` after all frames: the shutdown is finished
    and everything is still written."""
    _interrupt_on_call(monkeypatch, dhptam.system.System, "shutdown", 1)
    result = run(sim_desk_run, tmp_path, mode="frames", progress=False, max_frames=10)
    assert result.interrupted
    _check_outputs(tmp_path, 10)


def test_ctrl_c_during_the_whole_map_bundle_adjustment(
    sim_desk_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The interrupt lands while the map is adjusted after the last frame: everything is still
    written, and the run is marked interrupted."""
    _interrupt_on_call(monkeypatch, dhptam.system.System, "refine_map", 1)
    result = run(sim_desk_run, tmp_path, mode="frames", progress=False, max_frames=10)
    assert result.interrupted
    _check_outputs(tmp_path, 10)


def test_ctrl_c_while_the_outputs_are_written(
    sim_desk_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An interrupt between two output files: the writing is redone, so no file is missing
    or stale, and timing.json records the interrupt."""
    _interrupt_on_call(monkeypatch, dhptam.trajectory, "write_tum", 2)
    result = run(sim_desk_run, tmp_path, mode="frames", progress=False, max_frames=10)
    assert result.interrupted
    _check_outputs(tmp_path, 10)


def test_sigint_to_the_command_exits_130_and_keeps_the_outputs(sim_desk_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "dhptam", "run", "--sequence", str(sim_desk_run), "--out", str(out)]
    child = subprocess.Popen(
        [*cmd, "--mode", "frames", "--realtime", "-q"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # A shell running the tests in the background ignores SIGINT, and the child would
        # inherit that: give it the default disposition, as a terminal's process has.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    log = out / "run.log"
    deadline = time.monotonic() + 120
    # Wait until tracking has started (the first frame is written to the log by the core),
    # then press Ctrl-C; --realtime keeps the run going for at least the sequence's 1.2 s.
    while time.monotonic() < deadline and child.poll() is None:
        if log.is_file() and "run: " in log.read_text():
            break
        time.sleep(0.05)
    time.sleep(0.4)
    assert child.poll() is None, child.communicate()
    child.send_signal(signal.SIGINT)
    stdout, stderr = child.communicate(timeout=120)
    assert child.returncode == 130, stderr
    assert "Traceback" not in stderr, stderr
    assert "interrupted" in stdout + stderr
    timing = json.loads((out / "timing.json").read_text())
    assert timing["interrupted"] is True
    # The trajectory holds exactly the frames done; on a slow machine the interrupt may reach
    # the run only while it finishes (all 24 frames done), which timing.json still records.
    assert len(read_tum(out / "trajectory.tum")[0]) == timing["frames"] <= 24


def test_a_ctrl_c_after_the_last_check_of_the_loop_is_not_lost() -> None:
    """The deferred SIGINT handler of the tracking loop: a Ctrl-C that arrives after the loop's
    last check (while its threads are being closed) still interrupts when the block ends; a
    block without one ends normally."""
    from dhptam.run import _interrupts_between_frames

    def ctrl_c_after_the_last_check() -> None:
        with _interrupts_between_frames() as pending:
            signal.raise_signal(signal.SIGINT)  # deferred: only sets the flag
            assert pending()

    # Python's own Ctrl-C handler, as in a terminal (a shell running the tests in the
    # background ignores SIGINT, and the deferral leaves other handlers alone).
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with _interrupts_between_frames() as pending:
            assert not pending()
        with pytest.raises(KeyboardInterrupt):
            ctrl_c_after_the_last_check()
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)


# -- panics ----------------------------------------------------------------------------------------


def test_internal_error_is_a_dhptam_error_and_a_runtime_error() -> None:
    """What the binding raises for a Rust panic: catchable with ``except Exception`` (PyO3's
    own PanicException derives from BaseException and would escape it)."""
    assert issubclass(InternalError, DhptamError) and issubclass(InternalError, RuntimeError)
    assert InternalError.__module__ == "dhptam.errors"


def test_cli_reports_an_internal_error_with_exit_code_1(monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    """The CLI side of the panic conversion: InternalError (what the binding raises for a
    caught Rust panic) is a failure, exit 1, one line without a traceback; not exit 2, which
    would blame the user's input."""
    from dhptam import cli

    def bug(args: Any) -> int:
        raise InternalError("internal error in slam::track: index out of bounds (this is a dhptam bug)")

    monkeypatch.setattr(cli, "_config_command", bug)
    code = cli.main(["config"])
    assert code == 1
    err = capsys.readouterr().err
    assert "internal error in slam::track" in err and "Traceback" not in err

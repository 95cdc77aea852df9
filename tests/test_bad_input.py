"""Bad input through every ``dhptam`` command (issue 10).

Each case runs the real command line (:func:`dhptam.cli.main`) on a damaged input and checks
what a user sees: exit code 2 for usage and input errors, a one-line ``error:`` message on
stderr that names the file (and the field or line where there is one), and no Python
traceback. Cases the system handles gracefully (empty event windows, all-black or all-white
frames) are checked to run to the end with every output file written.

The loader-level corruption suite (every field of the TUM-VIE layout, chunk corruption) lives
in ``test_datasets_tumvie.py``; this file checks that the same failures surface cleanly
through the commands, and covers the commands' own inputs (configs, trajectories, problems).
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import tumvie_layout as tl

from dhptam.cli import main
from dhptam.trajectory import read_tum

SEQ = "mocap-desk"
EV_LEFT = f"{SEQ}-events_left.h5"
TS_LEFT = "left_images/image_timestamps_left.txt"


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> tl.Layout:
    """A small sequence in the real TUM-VIE layout (8 frame pairs, 128×96), written once."""
    root = tmp_path_factory.mktemp("pristine")
    return tl.write_sequence(root, np.random.default_rng(11), n_frames=8, n_events=30_000)


@pytest.fixture
def layout(pristine: tl.Layout, tmp_path: Path) -> tl.Layout:
    """A fresh copy of the sequence that a test may damage."""
    root = tmp_path / "data"
    shutil.copytree(pristine.root, root)
    return tl.Layout(
        root, pristine.name, root / pristine.name, pristine.frame_t_ns, pristine.exposure_ns, pristine.images
    )


def _cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """Exit code and stderr of one command; argparse's own exits are returned as codes."""
    try:
        code = main(argv)
    except SystemExit as exit_info:
        code = int(exit_info.code or 0)
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return code, err


def _run_argv(layout: tl.Layout, out: Path, *extra: str) -> list[str]:
    return [
        "run",
        "--sequence",
        str(layout.seq_dir),
        "--out",
        str(out),
        "-q",
        "--sync",
        "--mode",
        "frames",
        *extra,
    ]


def _truncate(path: Path, fraction: float) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])


def _edit_json(path: Path, edit: Callable[[dict], None]) -> None:
    doc = json.loads(path.read_text())
    edit(doc["value0"])
    path.write_text(json.dumps(doc))


def _edit_lines(path: Path, edit: Callable[[list[str]], list[str]]) -> None:
    path.write_text("\n".join(edit(path.read_text().splitlines())) + "\n")


def _swap(lines: list[str], i: int, j: int) -> list[str]:
    lines[i], lines[j] = lines[j], lines[i]
    return lines


def _rewrite_events(path: Path, **changes: np.ndarray | None) -> None:
    with h5py.File(path, "r") as f:
        data = {k: f[f"events/{k}"][:] for k in ("x", "y", "t", "p")}
    data.update(changes)
    with h5py.File(path, "w") as f:
        for key, value in data.items():
            if value is not None:
                f.create_dataset(f"events/{key}", data=value)


def _events_t(path: Path) -> np.ndarray:
    with h5py.File(path, "r") as f:
        return f["events/t"][:]


# -- dhptam run: damaged sequences that must be refused before any work -------------------------

# (id, damage, text the error must contain)
RUN_INPUT_ERRORS: list[tuple[str, Callable[[tl.Layout], object], str]] = [
    ("missing event file", lambda s: (s.seq_dir / EV_LEFT).unlink(), EV_LEFT),
    ("truncated event HDF5", lambda s: _truncate(s.seq_dir / EV_LEFT, 0.4), EV_LEFT),
    ("event file not HDF5", lambda s: (s.seq_dir / EV_LEFT).write_text("x,y,t,p\n1,2,3,1\n"), EV_LEFT),
    (
        "event dataset missing",
        lambda s: _rewrite_events(s.seq_dir / EV_LEFT, p=None),
        "events/p",
    ),
    (
        "event x of the wrong dtype",
        lambda s: _rewrite_events(s.seq_dir / EV_LEFT, x=np.zeros(10, np.float32)),
        "events/x",
    ),
    (
        "events in nanoseconds (wrong unit)",
        lambda s: _rewrite_events(s.seq_dir / EV_LEFT, t=_events_t(s.seq_dir / EV_LEFT) * 1000),
        EV_LEFT,
    ),
    ("calibration missing", lambda s: (s.root / "camera-calibrationA.json").unlink(), "camera-calibration"),
    (
        "calibration not JSON",
        lambda s: (s.root / "camera-calibrationA.json").write_text("{ value0: "),
        "camera-calibrationA.json",
    ),
    (
        "calibration truncated",
        lambda s: _truncate(s.root / "camera-calibrationA.json", 0.5),
        "camera-calibrationA.json",
    ),
    (
        "calibration NaN focal length",
        lambda s: _edit_json(
            s.root / "camera-calibrationA.json",
            lambda v: v["intrinsics"][0]["intrinsics"].update(fx=float("nan")),
        ),
        "value0.intrinsics[0].intrinsics.fx",
    ),
    (
        "calibration field missing",
        lambda s: _edit_json(s.root / "camera-calibrationA.json", lambda v: v.pop("T_imu_cam")),
        "T_imu_cam",
    ),
    (
        "unsorted frame timestamps",
        lambda s: _edit_lines(s.seq_dir / TS_LEFT, lambda ls: _swap(ls, 3, 4)),
        "image_timestamps_left.txt",
    ),
    (
        "duplicated frame timestamp",
        lambda s: _edit_lines(s.seq_dir / TS_LEFT, lambda ls: [*ls[:4], ls[3], *ls[5:]]),
        "image_timestamps_left.txt",
    ),
    (
        "garbage in a timestamp line",
        lambda s: _edit_lines(s.seq_dir / TS_LEFT, lambda ls: [*ls[:2], "12x34", *ls[3:]]),
        "image_timestamps_left.txt",
    ),
    (
        "dropped frame (image missing)",
        lambda s: (s.seq_dir / "left_images/00005.jpg").unlink(),
        "left_images",
    ),
    (
        "mocap file with NaN",
        lambda s: _edit_lines(
            s.seq_dir / "mocap_data.txt", lambda ls: [*ls[:3], ls[3].rsplit(" ", 1)[0] + " nan", *ls[4:]]
        ),
        "mocap_data.txt",
    ),
]


@pytest.mark.parametrize(
    ("damage", "names"), [c[1:] for c in RUN_INPUT_ERRORS], ids=[c[0] for c in RUN_INPUT_ERRORS]
)
def test_run_refuses_a_damaged_sequence(
    layout: tl.Layout,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    damage: Callable[[tl.Layout], object],
    names: str,
) -> None:
    damage(layout)
    code, err = _cli(_run_argv(layout, tmp_path / "out"), capsys)
    assert code == 2, err
    assert "dhptam run: error:" in err
    assert names in err, err


def test_run_on_the_pristine_copy_works(
    layout: tl.Layout, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The control for the cases above: the undamaged sequence runs to its end, so each
    refusal is due to its damage."""
    code, err = _cli(_run_argv(layout, tmp_path / "out"), capsys)
    assert code == 0, err
    assert len((tmp_path / "out" / "frames.csv").read_text().splitlines()) == 1 + 8


# -- dhptam run: damage met mid-run keeps everything done so far --------------------------------


@pytest.fixture
def desk(sim_desk_run: Path, tmp_path: Path) -> Path:
    """A copy of the simulated 1.2 s desk sequence (24 frame pairs, 320-pixel frames; tracks
    every frame when undamaged) that a test may damage."""
    copy = tmp_path / "desk" / sim_desk_run.name
    shutil.copytree(sim_desk_run, copy)
    return copy


def _desk_argv(seq: Path, out: Path, mode: str = "frames") -> list[str]:
    return [
        "run",
        "--sequence",
        str(seq),
        "--out",
        str(out),
        "-q",
        "--sync",
        "--mode",
        mode,
        "--max-frames",
        "12",
    ]


@pytest.mark.parametrize(
    ("damage", "names"),
    [
        (lambda d: (d / "left_images/00005.jpg").write_bytes(b"\xff\xd8 not a jpeg"), "00005.jpg"),
        (lambda d: cv2.imwrite(str(d / "right_images/00005.jpg"), np.zeros((50, 60), np.uint8)), "00005.jpg"),
    ],
    ids=["corrupt JPEG", "frame of the wrong size"],
)
def test_a_bad_frame_mid_run_is_an_input_error_and_keeps_the_frames_before(
    desk: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    damage: Callable[[Path], object],
    names: str,
) -> None:
    damage(desk)
    out = tmp_path / "out"
    code, err = _cli(_desk_argv(desk, out), capsys)
    assert code == 2, err
    assert names in err
    # Frames 0..4 were tracked before the bad frame 5; all of them are in the outputs.
    assert len(read_tum(out / "trajectory.tum")[0]) == 5
    timing = json.loads((out / "timing.json").read_text())
    assert timing["frames"] == 5 and names in timing["error"]
    assert not list(out.glob(".*tmp*")), "temporary files left behind"


# -- dhptam run: inputs handled gracefully ------------------------------------------------------


def _fill_images(seq: Path, value: int, frames: range) -> None:
    for side in ("left", "right"):
        for k in frames:
            path = seq / f"{side}_images/{k:05d}.jpg"
            h, w = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).shape
            cv2.imwrite(str(path), np.full((h, w), value, np.uint8))


def _drop_events_from(seq: Path, t_ns: int) -> None:
    for side in ("left", "right"):
        path = seq / f"{seq.name}-events_{side}.h5"
        with h5py.File(path, "r") as f:
            data = {k: f[f"events/{k}"][:] for k in ("x", "y", "t", "p")}
        keep = data["t"] * 1000 < t_ns
        _rewrite_events(path, **{k: v[keep] for k, v in data.items()})


def _frame_t_ns(seq: Path, k: int) -> int:
    lines = (seq / "left_images/image_timestamps_left.txt").read_text().split()
    return int(float([v for v in lines if v[:1].isdigit()][k]) * 1000)


@pytest.mark.parametrize("mode", ["frames", "fusion"])
@pytest.mark.parametrize(
    ("damage", "tracked"),
    [
        pytest.param(lambda d: _fill_images(d, 0, range(24)), range(0), id="all-black frames"),
        pytest.param(lambda d: _fill_images(d, 255, range(24)), range(0), id="all-white frames"),
        pytest.param(lambda d: _fill_images(d, 0, range(5, 8)), range(5), id="black frames mid-sequence"),
        pytest.param(lambda d: _drop_events_from(d, _frame_t_ns(d, 4)), range(12), id="empty event windows"),
    ],
)
def test_run_handles_featureless_input_gracefully(
    desk: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    damage: Callable[[Path], object],
    tracked: range,
    mode: str,
) -> None:
    """Documented behaviour: frames without features (black, saturated) and windows without
    events do not fail the run; those frames are reported ``lost`` (unless events carry them
    in ``fusion``), the frames with content are tracked, and every output file is written.
    Frame 0, whose event window ends a few milliseconds into the recording, is sensor noise:
    in ``fusion`` with failed frames its image is events only, and it is ``held`` at the pose
    of the first map instead of making one."""
    damage(desk)
    out = tmp_path / "out"
    code, err = _cli(_desk_argv(desk, out, mode), capsys)
    assert code == 0, err
    rows = (out / "frames.csv").read_text().splitlines()
    assert len(rows) == 1 + 12
    states = [r.split(",")[rows[0].split(",").index("state")] for r in rows[1:]]
    assert set(states) <= {"ok", "initialised", "lost", "relocalised", "held"}, states
    assert "held" not in states[1:], states
    assert all(states[k] != "lost" for k in tracked), states
    for name in ("trajectory.tum", "keyframes.tum", "map.ply", "timing.json", "config.toml"):
        assert (out / name).is_file()


# -- dhptam run: arguments and configuration ------------------------------------------------------


@pytest.mark.parametrize(
    ("config_text", "names"),
    [
        ("[tracking\nfoo = 1\n", "run.toml"),
        ("[triangulation]\nmin_dept_m = 0.3\n", "min_dept_m"),
        ('[triangulation]\nmin_depth_m = "near"\n', "min_depth_m"),
        ("[triangulation]\nmin_depth_m = nan\n", "min_depth_m"),
        ("[nonsense]\n", "nonsense"),
    ],
    ids=["not TOML", "unknown key", "wrong type", "NaN value", "unknown section"],
)
def test_run_with_a_bad_config_names_the_file_and_key(
    layout: tl.Layout, tmp_path: Path, capsys: pytest.CaptureFixture[str], config_text: str, names: str
) -> None:
    config = tmp_path / "run.toml"
    config.write_text(config_text)
    code, err = _cli(_run_argv(layout, tmp_path / "out", "--config", str(config)), capsys)
    assert code == 2, err
    assert names in err, err


@pytest.mark.parametrize(
    ("argv_edit", "names"),
    [
        (lambda a, t: [*a[:2], str(t / "nope"), *a[3:]], "sequence folder not found"),
        (lambda a, t: [*a[:2], str(t / "file.txt"), *a[3:]], "file.txt"),
        (lambda a, t: [*a, "--config", str(t / "missing.toml")], "missing.toml"),
        (lambda a, t: [*a, "--calibration", str(t / "missing.json")], "missing.json"),
        (lambda a, t: [*a[:4], str(t / "file.txt"), *a[5:]], "file.txt"),
        (lambda a, t: [*a, "--max-frames", "-3"], "max_frames"),
        (lambda a, t: [*a, "--features", "surf"], "surf"),
        (lambda a, t: [*a, "--max-frames", "many"], "many"),
    ],
    ids=[
        "sequence missing",
        "sequence is a file",
        "config missing",
        "calibration missing",
        "output is a file",
        "negative max-frames",
        "unknown extractor",
        "max-frames not a number",
    ],
)
def test_run_usage_errors(
    layout: tl.Layout, tmp_path: Path, capsys: pytest.CaptureFixture[str], argv_edit, names: str
) -> None:
    (tmp_path / "file.txt").write_text("not a folder\n")
    code, err = _cli(argv_edit(_run_argv(layout, tmp_path / "out"), tmp_path), capsys)
    assert code == 2, err
    assert names in err, err


# -- the other commands ---------------------------------------------------------------------------


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


TUM_OK = "# t x y z qx qy qz qw\n" + "".join(f"{0.1 * k:.1f} {0.01 * k} 0 0 0 0 0 1\n" for k in range(20))


@pytest.mark.parametrize(
    ("files", "argv", "names"),
    [
        (
            {},
            ["eval", "--estimate", "{d}/nope.tum", "--reference", "{d}/ref.tum", "--out", "{d}/o"],
            "nope.tum",
        ),
        (
            {"est.tum": "0.0 0 0 0 0 0 0 1\n0.1 0 0 zero 0 0 0 1\n"},
            ["eval", "--estimate", "{d}/est.tum", "--reference", "{d}/ref.tum", "--out", "{d}/o"],
            "est.tum",
        ),
        (
            {"est.tum": "0.0 0 0 0 0 0 0 1\n0.1 0 0 nan 0 0 0 1\n"},
            ["eval", "--estimate", "{d}/est.tum", "--reference", "{d}/ref.tum", "--out", "{d}/o"],
            "est.tum",
        ),
        (
            {"est.tum": "0.5 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1\n0.3 0 0 0 0 0 0 1\n"},
            ["eval", "--estimate", "{d}/est.tum", "--reference", "{d}/ref.tum", "--out", "{d}/o"],
            "est.tum",
        ),
        (
            {"est.tum": "# empty\n"},
            ["eval", "--estimate", "{d}/est.tum", "--reference", "{d}/ref.tum", "--out", "{d}/o"],
            "est.tum",
        ),
        (
            {"est.tum": "".join(f"{100 + 0.1 * k:.1f} 0 0 0 0 0 0 1\n" for k in range(5))},
            ["eval", "--estimate", "{d}/est.tum", "--reference", "{d}/ref.tum", "--out", "{d}/o"],
            "fall inside the reference",
        ),
        ({}, ["eval", "--suite", "{d}/missing-suite.toml", "--out", "{d}/o"], "missing-suite.toml"),
        ({"suite.toml": "[[runs\n"}, ["eval", "--suite", "{d}/suite.toml", "--out", "{d}/o"], "suite.toml"),
        ({}, ["solve", "bal", "{d}/nope.txt"], "nope.txt"),
        ({"p.txt": "2 3 4\n0 0 1.0 2.0\n"}, ["solve", "bal", "{d}/p.txt"], "p.txt"),
        ({"p.txt": "1 1 1\n0 0 nan 2.0\n" + "0\n" * 12}, ["solve", "bal", "{d}/p.txt"], "p.txt"),
        ({"g.g2o": "VERTEX_SE3:QUAT 0 0 0 0 0 0 0\n"}, ["solve", "pose-graph", "{d}/g.g2o"], "g.g2o"),
        ({"g.g2o": "EDGE_SE2 0 7 1 0 0 1 0 0 1 0 1\n"}, ["solve", "pose-graph", "{d}/g.g2o"], "g.g2o"),
        ({}, ["config", "--check", "{d}/missing.toml"], "missing.toml"),
        ({"c.toml": "[log]\nlevel = 3\n"}, ["config", "--check", "{d}/c.toml"], "level"),
        (
            {"traj.tum": "0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0\n"},
            ["simulate", "--preset", "tiny", "--out", "{d}/s", "--trajectory", "{d}/traj.tum", "--quiet"],
            "traj.tum",
        ),
        (
            {"traj.csv": "0,0,0,0,0,0,0,1\n100,0,0,0,0,0,0,1\n50,0,0,0,0,0,0,1\n"},
            ["simulate", "--preset", "tiny", "--out", "{d}/s", "--trajectory", "{d}/traj.csv", "--quiet"],
            "traj.csv",
        ),
        ({}, ["simulate", "--preset", "tiny", "--out", "{d}/s", "--duration", "-1", "--quiet"], "duration"),
        (
            {"s": "a file where the output folder should go\n"},
            ["simulate", "--preset", "tiny", "--out", "{d}/s", "--duration", "0.1", "--quiet"],
            "s",
        ),
        ({}, ["simulate", "--preset", "tiny", "--out", "{d}/s", "--blackout", "1"], "START:DURATION"),
        ({}, ["simulate", "--preset", "tiny", "--out", "{d}/s", "--shake", "0.2:-1", "--quiet"], "shake"),
        ({}, ["simulate", "--preset", "tiny", "--out", "{d}/s", "--pause", "0.2:0", "--quiet"], "pause"),
        ({}, ["calibrate-align", "--sequence", "{d}/nope", "--out", "{d}/a.toml"], "nope"),
        ({}, ["demo", "--out", "{d}/demo", "--modes", "frames,dreams", "-q"], "dreams"),
        ({}, ["solve", "bal"], "FILE"),
        ({}, ["frobnicate"], "frobnicate"),
    ],
    ids=[
        "eval estimate missing",
        "eval estimate not a number",
        "eval estimate NaN",
        "eval estimate unsorted",
        "eval estimate empty",
        "eval no time overlap",
        "eval suite missing",
        "eval suite not TOML",
        "solve BAL missing",
        "solve BAL truncated",
        "solve BAL NaN",
        "solve g2o short vertex",
        "solve g2o edge to unknown vertex",
        "config check missing",
        "config check wrong type",
        "simulate trajectory short row",
        "simulate trajectory unsorted",
        "simulate negative duration",
        "simulate output is a file",
        "simulate blackout not a span",
        "simulate negative shake duration",
        "simulate empty pause",
        "calibrate-align sequence missing",
        "demo unknown mode",
        "solve without a file",
        "unknown command",
    ],
)
def test_commands_report_bad_input_with_exit_code_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], files: dict[str, str], argv: list[str], names: str
) -> None:
    _write(tmp_path / "ref.tum", TUM_OK)
    for name, text in files.items():
        _write(tmp_path / name, text)
    code, err = _cli([a.format(d=tmp_path) for a in argv], capsys)
    assert code == 2, err
    assert names in err, err


# -- panics never cross the Python boundary -------------------------------------------------------


def test_a_core_panic_becomes_internal_error_and_the_process_lives_on() -> None:
    """The binding's panic guard (``detach_guarded``) on a real Rust panic: the test-only
    ``_core._testing_panic`` panics inside it with the given message."""
    from dhptam import _core
    from dhptam.errors import DhptamError, InternalError

    for attempt in range(2):  # a second panic after the first: nothing was left poisoned
        with pytest.raises(InternalError) as err:
            _core._testing_panic(f"deliberate panic #{attempt} for the test")
        message = str(err.value)
        assert f"deliberate panic #{attempt} for the test" in message
        assert "internal error in _testing_panic" in message and "dhptam bug" in message
    # An ordinary `except Exception` catches it (PyO3's PanicException is a BaseException).
    with pytest.raises(Exception) as caught:  # noqa: PT011 (the point of the test)
        _core._testing_panic("caught as Exception")
    assert isinstance(caught.value, DhptamError) and isinstance(caught.value, RuntimeError)
    # The interpreter and the extension still work: a core call after the panics succeeds.
    assert _core.thread_count() >= 1

"""Visualisation: ``dhptam run --viz rerun``, ``dhptam view`` and their helpers (``dhptam.viz``).

Recordings are read back with rerun's own chunk reader and checked entity by entity.
"""

from __future__ import annotations

import csv
import json
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rerun.chunk import RrdReader

import dhptam
from dhptam.cli import main
from dhptam.depth import write_ply
from dhptam.run import run
from dhptam.trajectory import read_tum
from dhptam.viz import RerunSink, align_positions, read_ply_points, view

PER_FRAME = (
    "/world/camera",
    "/world/camera/image/fused",
    "/images/frame",
    "/images/e3ct",
    "/images/stereo",
    "/images/stereo/keypoints",
    "/images/stereo/matches",
    "/plots/beta",
    "/plots/mode",
    "/plots/inliers",
    "/plots/keypoints",
)
FINAL = (
    "/world/trajectory/estimate",
    "/world/trajectory/ground_truth",
    "/world/keyframes",
    "/world/map",
    "/world/loops",
)


def _read(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Entity path → one dict per logged row (column name → value), static rows included."""
    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        table = chunk.to_record_batch().to_pydict()
        for i in range(chunk.num_rows):
            rows[chunk.entity_path].append({k: v[i] for k, v in table.items()})
    return rows


def _column(rows: list[dict[str, Any]], suffix: str) -> list[Any]:
    """The values of the one column whose name ends with ``suffix`` (e.g. ``:positions``)."""
    names = {k for r in rows for k in r if k.endswith(suffix)}
    assert len(names) == 1, (suffix, names)
    (name,) = names
    return [r[name] for r in rows if r.get(name) is not None]


def _sensor_ns(rows: list[dict[str, Any]]) -> list[int]:
    values = [r["sensor_time"] for r in rows]
    return [int(v.value) if hasattr(v, "value") else int(v / np.timedelta64(1, "ns")) for v in values]


@pytest.fixture(scope="module")
def viz_run(sim_desk_run: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Any]:
    out = tmp_path_factory.mktemp("viz") / "run"
    result = run(sim_desk_run, out, mode="fusion", progress=False, threaded=False, max_frames=12, viz="rerun")
    return out, result


def test_run_with_viz_rerun_records_every_entity(viz_run: tuple[Path, Any]) -> None:
    out, result = viz_run
    assert result.files["recording"] == out / "recording.rrd"
    rows = _read(out / "recording.rrd")
    frames = list(csv.DictReader((out / "frames.csv").read_text().splitlines()))
    assert result.frames == len(frames) == 12
    for entity in PER_FRAME:
        assert len(rows[entity]) == 12, entity
    # The timeline is sensor time: the frames' own timestamps, in order.
    t_ns, _ = read_tum(out / "trajectory.tum")
    assert _sensor_ns(rows["/world/camera"]) == [round(float(f["t_s"]) * 1e9) for f in frames]
    assert np.allclose(np.array(_sensor_ns(rows["/world/camera"])), t_ns, atol=1)
    assert [r["frame"] for r in rows["/plots/beta"]] == [int(f["index"]) for f in frames]
    betas = [v[0] for v in _column(rows["/plots/beta"], ":scalars")]
    assert np.allclose(betas, [float(f["beta_left"]) for f in frames], atol=1e-4)
    inliers = [v[0] for v in _column(rows["/plots/inliers"], ":scalars")]
    assert inliers == [float(f["inliers"]) for f in frames]
    # Keypoints: left and right of every frame.
    counts = [len(v) for v in _column(rows["/images/stereo/keypoints"], ":positions")]
    assert counts == [int(f["keypoints_left"]) + int(f["keypoints_right"]) for f in frames]
    # Stereo matches: segments from a left keypoint to a right one on the same rectified row.
    per_frame = _column(rows["/images/stereo/matches"], ":strips")
    strips = [np.asarray(s, np.float64) for v in per_frame for s in v]
    assert len(strips) > 12 * 20, "too few stereo matches drawn"
    segments = np.stack(strips)
    assert np.all(np.abs(segments[:, 0, 1] - segments[:, 1, 1]) <= 2.0 + 1e-4)
    # Final state, logged once: as many map points and keyframes as the run reports.
    for entity in FINAL:
        assert len(rows[entity]) == 1, entity
    assert len(_column(rows["/world/map"], ":positions")[0]) == result.map_points > 0
    assert len(_column(rows["/world/keyframes"], ":positions")[0]) == result.keyframes > 0
    estimate = np.asarray(_column(rows["/world/trajectory/estimate"], ":strips")[0][0])
    assert estimate.shape == (12, 3)
    # The aligned ground truth lies on the estimate (a working tracker: centimetres).
    gt = np.asarray(_column(rows["/world/trajectory/ground_truth"], ":strips")[0][0])
    assert len(gt) >= 12
    nearest = np.min(np.linalg.norm(estimate[:, None, :] - gt[None, :, :], axis=2), axis=1)
    assert np.median(nearest) < 0.05, nearest
    assert json.loads((out / "timing.json").read_text())["sequence"]


def test_view_copies_an_existing_recording(viz_run: tuple[Path, Any], tmp_path: Path) -> None:
    out, _ = viz_run
    target = tmp_path / "copy.rrd"
    assert main(["view", str(out), "--save", str(target)]) == 0
    assert target.read_bytes() == (out / "recording.rrd").read_bytes()


def test_view_builds_a_recording_from_a_run_without_one(sim_desk_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = run(sim_desk_run, out, mode="frames", progress=False, threaded=False, max_frames=10)
    assert "recording" not in result.files and not (out / "recording.rrd").exists()
    path, shown = view(out, spawn=False)
    assert path == out / "view.rrd" and not shown
    rows = _read(path)
    assert len(rows["/world/camera"]) == 10
    assert len(rows["/plots/inliers"]) == 10
    assert "/images/frame" not in rows
    map_points = read_ply_points(out / "map.ply")
    assert len(map_points) == result.map_points > 0
    assert np.allclose(np.asarray(_column(rows["/world/map"], ":positions")[0]), map_points, atol=1e-6)
    kt, _ = read_tum(out / "keyframes.tum")
    assert len(_column(rows["/world/keyframes"], ":positions")[0]) == len(kt)
    # The sequence's ground truth was found through timing.json and drawn.
    assert len(rows["/world/trajectory/ground_truth"]) == 1
    # --save elsewhere, through the CLI.
    saved = tmp_path / "saved.rrd"
    assert main(["view", str(out), "--save", str(saved)]) == 0
    assert len(_read(saved)["/world/camera"]) == 10
    # Without the sequence's location no ground truth is drawn, unless --reference names one.
    timing = json.loads((out / "timing.json").read_text())
    del timing["sequence"]
    (out / "timing.json").write_text(json.dumps(timing))
    view(out, save=tmp_path / "no-gt.rrd", spawn=False)
    assert "/world/trajectory/ground_truth" not in _read(tmp_path / "no-gt.rrd")
    reference = sim_desk_run / "groundtruth_frame_left.txt"
    assert main(["view", str(out), "--save", str(tmp_path / "gt.rrd"), "--reference", str(reference)]) == 0
    assert len(_read(tmp_path / "gt.rrd")["/world/trajectory/ground_truth"]) == 1


def test_view_errors_name_the_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nowhere"
    assert main(["view", str(missing), "--no-spawn"]) == 2
    assert f"{missing}: run folder not found" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["view", str(tmp_path / "empty"), "--no-spawn"]) == 2
    assert "neither recording.rrd nor trajectory.tum" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["run", "--sequence", str(tmp_path), "--out", str(tmp_path), "--viz", "vr-headset"])
    assert exit_info.value.code == 2


def test_align_positions_recovers_a_known_rigid_motion() -> None:
    rng = np.random.default_rng(3)
    source = rng.normal(size=(50, 3))
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    translation = np.array([0.3, -1.2, 2.0])
    r, t = align_positions(source, source @ rotation.T + translation)
    assert np.allclose(r, rotation, atol=1e-10) and np.allclose(t, translation, atol=1e-10)
    # A reflection is never returned.
    r, _ = align_positions(source, source * np.array([1.0, 1.0, -1.0]))
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_read_ply_points_round_trips_write_ply(tmp_path: Path) -> None:
    points = np.random.default_rng(0).normal(size=(40, 3))
    write_ply(str(tmp_path / "a.ply"), points)
    write_ply(str(tmp_path / "b.ply"), points, np.full((40, 3), 7, np.uint8))
    for name in ("a.ply", "b.ply"):
        assert np.allclose(read_ply_points(tmp_path / name), points.astype(np.float32))
    (tmp_path / "bad.ply").write_bytes(b"not a ply")
    from dhptam.errors import InputError

    with pytest.raises(InputError, match="not a PLY file"):
        read_ply_points(tmp_path / "bad.ply")


class _FakeClock:
    """Stands in for the ``time`` module of ``dhptam.run``: the clock only moves when slept."""

    def __init__(self) -> None:
        self.now = 0.0
        self.slept: list[float] = []

    def perf_counter(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        self.now += seconds


@pytest.mark.parametrize("realtime", [True, False])
def test_realtime_feeds_frames_at_the_sensor_rate(
    realtime: bool, sim_desk_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    clock = _FakeClock()
    monkeypatch.setattr(sys.modules["dhptam.run"], "time", clock)
    # Through the package-level entry point for scripts, dhptam.run(...) -> RunResult.
    result = dhptam.run(
        sim_desk_run, tmp_path, progress=False, max_frames=6, realtime=realtime, threaded=False
    )
    assert isinstance(result, dhptam.RunResult)
    assert result.frames == 6
    t_ns, _ = read_tum(tmp_path / "trajectory.tum")
    if realtime:
        # With a clock that stands still while working, frame k waits until t_k - t_0 of
        # playback time has passed: one wait per frame after the first, in total the span.
        assert len(clock.slept) == 5
        assert sum(clock.slept) == pytest.approx((t_ns[-1] - t_ns[0]) / 1e9, abs=1e-9)
        assert np.allclose(clock.slept, np.diff(t_ns) / 1e9, atol=1e-9)
    else:
        assert clock.slept == []


def test_a_failure_on_the_viz_thread_reaches_the_caller(tmp_path: Path) -> None:
    sink = RerunSink(tmp_path / "broken.rrd", (100.0, 100.0, 50.0, 50.0, 0.1, 100, 100))
    sink.frame(object(), None, None, None)  # no images: logging it fails on the sink's thread
    with pytest.raises(AttributeError):
        sink.close()

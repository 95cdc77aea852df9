"""TumVieWriter: what it writes is the TUM-VIE layout, the loader reads it back unchanged, and
a failed or refused write leaves nothing behind."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import hdf5plugin
import numpy as np
import pytest

from dhptam import SE3, Camera, FileError, InputError
from dhptam.datasets import CAMERA_KEYS, RigCalibration, TumVieWriter, load_tumvie

W, H = 96, 64  # frame cameras
EW, EH = 120, 80  # event cameras


def make_rig(rng: np.random.Generator) -> RigCalibration:
    cameras = {
        "frame_left": Camera("kb4", [80.0, 80.5, 47.5, 31.5, 0.02, -0.01, 0.003, -0.001], W, H),
        "frame_right": Camera("radtan", [81.0, 80.0, 48.0, 32.0, -0.1, 0.02, 0.001, -0.002, 0.005], W, H),
        "event_left": Camera("kb4", [90.0, 90.0, 59.5, 39.5, -0.01, 0.0, 0.002, 0.0], EW, EH),
        "event_right": Camera("pinhole", [91.0, 90.5, 60.0, 40.0], EW, EH),
    }
    extrinsics = {k: SE3.exp(rng.normal(size=6) * 0.2) for k in CAMERA_KEYS}
    return RigCalibration(cameras, extrinsics)


def smooth_image(rng: np.random.Generator) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    a, b, c = rng.uniform(4, 15, 3)
    return (128 + 90 * np.sin(xx / a + c) * np.cos(yy / b)).astype(np.uint8)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(float) - b.astype(float)) ** 2)
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


def random_event_chunks(rng: np.random.Generator, n_chunks: int, per_chunk: int):
    """Sorted chunks, ns times that are not whole µs, gaps of several ms between chunks."""
    t = 3_000_000  # ns
    for _ in range(n_chunks):
        times = t + np.sort(rng.integers(0, 7_000_000, per_chunk))
        t = int(times[-1]) + int(rng.integers(0, 5_000_000))
        yield (
            rng.integers(0, EW, per_chunk).astype(np.uint16),
            rng.integers(0, EH, per_chunk).astype(np.uint16),
            times.astype(np.int64),
            rng.integers(0, 2, per_chunk).astype(np.int8),
        )


def test_round_trip(tmp_path: Path, rng: np.random.Generator):
    rig = make_rig(rng)
    imu_from_marker = SE3.exp(rng.normal(size=6) * 0.3)
    frame_t = 1_000_000 + np.cumsum(rng.integers(40_000_000, 60_000_000, 8))  # ns, not whole µs
    exposures = rng.integers(100_000, 20_000_000, 8)
    images = [(smooth_image(rng), smooth_image(rng)) for _ in frame_t]
    chunks = {side: list(random_event_chunks(rng, 12, 3000)) for side in ("left", "right")}
    mocap_t = np.arange(0, 400_000_000, 8_333_333, dtype=np.int64)
    q = rng.normal(size=(len(mocap_t), 4))
    mocap = np.hstack([rng.normal(size=(len(mocap_t), 3)), q / np.linalg.norm(q, axis=1, keepdims=True)])

    with TumVieWriter(tmp_path, "sim-desk", rig, imu_from_marker) as writer:
        for t, e, (left, right) in zip(frame_t, exposures, images, strict=True):
            writer.add_frame_pair(int(t), int(e), left, right)
        for k in range(12):  # interleave the two cameras, as a simulator would
            for side in ("left", "right"):
                writer.add_events(side, *chunks[side][k])
        writer.set_mocap(mocap_t, mocap)
        writer.add_text_file("sim-desk-gt-left-frame.tum", "# t x y z qx qy qz qw\n")
        with pytest.raises(InputError):
            writer.add_text_file("../escape.txt", "")
    seq_dir = tmp_path / "sim-desk"
    assert (seq_dir / "sim-desk-gt-left-frame.tum").read_text() == "# t x y z qx qy qz qw\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim-desk"]  # no temporary left over

    # The real layout, file by file.
    names = {p.relative_to(seq_dir).as_posix() for p in seq_dir.rglob("*")}
    for expected in (
        "sim-desk-events_left.h5",
        "sim-desk-events_right.h5",
        "left_images/00000.jpg",
        "right_images/00007.jpg",
        "left_images/image_timestamps_left.txt",
        "right_images/image_exposures_right.txt",
        "mocap_data.txt",
        "camera-calibrationA.json",
        "mocap-imu-calibrationA.json",
    ):
        assert expected in names
    with h5py.File(seq_dir / "sim-desk-events_left.h5", "r") as f:
        assert {k: f[f"events/{k}"].dtype for k in "xytp"} == {
            "x": np.uint16,
            "y": np.uint16,
            "t": np.int64,
            "p": np.int8,
        }
        assert f["ms_to_idx"].dtype == np.uint64
        for name in ("events/x", "events/y", "events/t", "events/p", "ms_to_idx"):
            plist = f[name].id.get_create_plist()
            filters = [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]
            assert filters == [hdf5plugin.BLOSC_ID] and f[name].chunks is not None
        t_us = f["events/t"][:]
        index = f["ms_to_idx"][:]
        # The DSEC definition, checked over the whole index.
        np.testing.assert_array_equal(index, np.searchsorted(t_us, 1000 * np.arange(len(index)), side="left"))
        assert index[-1] == len(t_us) and 1000 * (len(index) - 1) > t_us[-1]
    assert (
        (seq_dir / "mocap_data.txt").read_text().startswith("# mocap poses: time(us) px py pz qx qy qz qw\n")
    )
    basalt = json.loads((seq_dir / "camera-calibrationA.json").read_text())["value0"]
    assert [c["camera_type"] for c in basalt["intrinsics"]] == ["kb4", "pinhole-radtan8", "kb4", "pinhole"]
    assert basalt["resolution"] == [[W, H], [W, H], [EW, EH], [EW, EH]]

    with load_tumvie(seq_dir) as seq:
        for key in CAMERA_KEYS:
            a, b = seq.calibration.cameras[key], rig.cameras[key]
            assert (a.model, a.width, a.height) == (b.model, b.width, b.height)
            np.testing.assert_array_equal(a.params, b.params)
            np.testing.assert_allclose(
                seq.calibration.imu_from_cam[key].matrix(), rig.imu_from_cam[key].matrix(), atol=1e-15
            )
        np.testing.assert_array_equal(seq.frames.t_ns, frame_t)
        np.testing.assert_array_equal(seq.frames.exposure_ns, exposures)
        for pair, (left, right) in zip(seq.frames, images, strict=True):
            assert psnr(pair.left, left) > 40 and psnr(pair.right, right) > 40
        for side in ("left", "right"):
            x, y, t, p = (np.concatenate(c) for c in zip(*chunks[side], strict=True))
            window = seq.events[side].window(-1, 10**12)
            np.testing.assert_array_equal(window.t_ns, t // 1000 * 1000)  # whole µs, rounded down
            np.testing.assert_array_equal(window.x, x)
            np.testing.assert_array_equal(window.y, y)
            np.testing.assert_array_equal(window.p, p)
            # Windows through the written index agree with the brute-force answer.
            for t0, t1 in np.sort(rng.integers(0, int(t[-1]) + 2_000_000, (50, 2)), axis=1):
                got = seq.events[side].window(int(t0), int(t1)).t_ns
                stored = t // 1000 * 1000
                np.testing.assert_array_equal(got, stored[(stored >= t0) & (stored < t1)])
        # Ground truth: the hand-eye chain applied to the mocap poses.
        gt = seq.ground_truth
        np.testing.assert_array_equal(gt.t_ns, mocap_t)
        marker_from_cam = imu_from_marker.inverse().matrix() @ rig.imu_from_cam["frame_left"].matrix()
        for row, marker in zip(gt.world_from_cam, mocap, strict=True):
            world_from_marker = SE3.from_translation_quat_xyzw(marker[:3], marker[3:]).matrix()
            got = SE3.from_translation_quat_xyzw(row[:3], row[3:]).matrix()
            np.testing.assert_allclose(got, world_from_marker @ marker_from_cam, atol=1e-12)
        np.testing.assert_allclose(seq.imu_from_marker.matrix(), imu_from_marker.matrix(), atol=1e-15)


def test_an_error_inside_the_context_leaves_nothing(tmp_path: Path, rng: np.random.Generator):
    rig = make_rig(rng)

    def simulate() -> None:
        with TumVieWriter(tmp_path, "seq", rig, SE3()) as writer:
            writer.add_frame_pair(0, 1000, smooth_image(rng), smooth_image(rng))
            writer.add_events("left", *next(random_event_chunks(rng, 1, 100)))
            raise RuntimeError("simulator crashed")

    with pytest.raises(RuntimeError, match="simulator crashed"):
        simulate()
    assert list(tmp_path.iterdir()) == []


def test_a_refused_write_leaves_nothing(tmp_path: Path, rng: np.random.Generator):
    rig = make_rig(rng)
    with pytest.raises(InputError), TumVieWriter(tmp_path, "seq", rig, SE3()) as writer:
        writer.add_frame_pair(0, 1000, np.zeros((H + 1, W), np.uint8), smooth_image(rng))
    assert list(tmp_path.iterdir()) == []


def test_existing_sequences_are_kept_unless_overwrite(tmp_path: Path, rng: np.random.Generator):
    rig = make_rig(rng)
    TumVieWriter(tmp_path, "seq", rig, SE3()).close()
    with pytest.raises(FileError, match="already exists") as info:
        TumVieWriter(tmp_path, "seq", rig, SE3())
    assert info.value.path == str(tmp_path / "seq")
    with TumVieWriter(tmp_path, "seq", rig, SE3(), overwrite=True) as writer:
        writer.add_frame_pair(5, 1, smooth_image(rng), smooth_image(rng))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]
    with load_tumvie(tmp_path / "seq") as seq:
        assert len(seq.frames) == 1 and seq.ground_truth is None
        assert len(seq.events["left"]) == 0 and seq.events["left"].has_index


def test_bad_writes_are_refused(tmp_path: Path, rng: np.random.Generator):
    rig = make_rig(rng)
    writer = TumVieWriter(tmp_path, "seq", rig, SE3())
    x, y, t, p = next(random_event_chunks(rng, 1, 100))
    writer.add_events("left", x, y, t, p)

    def refused(field: str, call, *args) -> None:
        with pytest.raises(InputError) as info:
            call(*args)
        assert info.value.field == field

    refused("side", writer.add_events, "middle", x, y, t, p)
    refused("t_ns", writer.add_events, "left", x, y, t - 10**6, p)  # earlier than what was written
    refused("t_ns", writer.add_events, "left", x, y, t[::-1] + 10**9, p)  # unsorted
    refused("t_ns", writer.add_events, "right", x, y, t - 10**9, p)  # negative
    refused("x", writer.add_events, "right", x + EW, y, t, p)
    refused("y", writer.add_events, "right", x, y + EH, t, p)
    refused("p", writer.add_events, "right", x, y, t, p * 2 - 1)  # ±1 is not the format's 0/1
    refused("t_ns", writer.add_events, "right", x, y, t.astype(np.float64), p)
    refused("events", writer.add_events, "right", x, y[:-1], t, p)
    t_frame = int(t[0])  # inside the events' span: the reader refuses disjoint clocks
    writer.add_frame_pair(t_frame, 5, smooth_image(rng), smooth_image(rng))
    refused("t_ns", writer.add_frame_pair, t_frame, 5, smooth_image(rng), smooth_image(rng))
    refused("exposure_ns", writer.add_frame_pair, t_frame + 10, -1, smooth_image(rng), smooth_image(rng))
    refused(
        "left",
        writer.add_frame_pair,
        t_frame + 10,
        5,
        smooth_image(rng).astype(np.float32),
        smooth_image(rng),
    )
    refused("world_from_marker", writer.set_mocap, np.arange(3), np.zeros((3, 6)))
    refused("t_ns", writer.set_mocap, np.array([0, 2, 1]), np.tile([0, 0, 0, 0, 0, 0, 1.0], (3, 1)))
    refused("world_from_marker", writer.set_mocap, np.arange(2), np.full((2, 7), np.nan))
    path = writer.close()
    # The refused calls changed nothing: the sequence holds exactly the accepted data.
    with load_tumvie(path) as seq:
        assert len(seq.events["left"]) == 100 and len(seq.events["right"]) == 0 and len(seq.frames) == 1
    refused("writer", writer.add_events, "left", x, y, t + 10**9, p)


def test_the_calibration_must_name_four_cameras(rng: np.random.Generator):
    rig = make_rig(rng)
    with pytest.raises(InputError, match="event_right") as info:
        RigCalibration({k: v for k, v in rig.cameras.items() if k != "event_right"}, rig.imu_from_cam)
    assert info.value.field == "cameras"

"""The TUM-VIE loader on sequences written in the real layout by the test itself, and on every
corrupt variant the loader documents."""

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

from dhptam import SE3, Camera, FileError, InputError, ParseError
from dhptam.datasets import CAMERA_KEYS, RigCalibration, load_tumvie


@pytest.fixture
def layout(tmp_path: Path, rng: np.random.Generator) -> tl.Layout:
    return tl.write_sequence(tmp_path, rng)


def se3(t: list[float], q: list[float]) -> np.ndarray:
    return SE3.from_translation_quat_xyzw(t, tl.unit(q)).matrix()


def matrix_from_row(row: np.ndarray) -> np.ndarray:
    return SE3.from_translation_quat_xyzw(row[:3], row[3:]).matrix()


# ---------------------------------------------------------------------------------------------
# the real layout loads
# ---------------------------------------------------------------------------------------------


def test_calibration_is_read_from_the_parent_folder(layout: tl.Layout):
    with load_tumvie(layout.seq_dir) as seq:
        assert seq.name == layout.name
        for i, key in enumerate(CAMERA_KEYS):
            cam = seq.calibration.cameras[key]
            assert cam.model == "kb4"
            assert (cam.width, cam.height) == tuple(tl.RESOLUTIONS[i])
            np.testing.assert_allclose(cam.params, tl.INTRINSICS[i], rtol=0, atol=1e-12)
            np.testing.assert_allclose(
                seq.calibration.imu_from_cam[key].matrix(), se3(*tl.T_IMU_CAM[i]), atol=1e-12
            )
        np.testing.assert_allclose(seq.imu_from_marker.matrix(), se3(*tl.T_IMU_MARKER), atol=1e-12)


def test_frames_have_exact_ns_stamps_and_lazily_decoded_images(layout: tl.Layout):
    with load_tumvie(layout.seq_dir) as seq:
        frames = seq.frames
        assert len(frames) == len(layout.frame_t_ns)
        # Sub-µs fractions in the text files survive exactly.
        np.testing.assert_array_equal(frames.t_ns, layout.frame_t_ns)
        np.testing.assert_array_equal(frames.exposure_ns, layout.exposure_ns)
        np.testing.assert_array_equal(frames.t_mid_ns, layout.frame_t_ns + layout.exposure_ns // 2)
        pairs = list(frames)
        assert [p.index for p in pairs] == list(range(len(frames)))
        for k, pair in enumerate(pairs):
            assert pair.t_ns == layout.frame_t_ns[k] and pair.exposure_ns == layout.exposure_ns[k]
            assert pair.t_mid_ns == pair.t_ns + pair.exposure_ns // 2
            for side, image in (("left", pair.left), ("right", pair.right)):
                assert image.dtype == np.uint8 and image.shape == (96, 128)
                error = np.abs(image.astype(int) - layout.images[side][k].astype(int))
                assert error.mean() < 1.5 and error.max() <= 12  # JPEG at quality 95
        assert frames[-1].index == len(frames) - 1
        with pytest.raises(IndexError):
            frames[len(frames)]


def test_events_load_with_their_dtypes(layout: tl.Layout):
    with load_tumvie(layout.seq_dir) as seq:
        for side in ("left", "right"):
            source = seq.events[side]
            x, y, t_us, p = layout.events[side]
            assert len(source) == len(t_us) and source.has_index
            assert source.t_range_ns == (int(t_us[0]) * 1000, int(t_us[-1]) * 1000 + 1)
            window = source.window(*source.t_range_ns)
            assert window.x.dtype == np.uint16 and window.y.dtype == np.uint16
            assert window.t_ns.dtype == np.int64 and window.p.dtype == np.int8
            np.testing.assert_array_equal(window.t_ns, t_us * 1000)
            np.testing.assert_array_equal(window.x, x)
            np.testing.assert_array_equal(window.y, y)
            np.testing.assert_array_equal(window.p, p)


def test_ground_truth_is_the_left_frame_camera_through_the_hand_eye_chain(layout: tl.Layout):
    with load_tumvie(layout.seq_dir) as seq:
        gt = seq.ground_truth
        assert gt is not None
        np.testing.assert_array_equal(gt.t_ns, layout.mocap_t_ns)
        imu_from_marker = se3(*tl.T_IMU_MARKER)
        imu_from_cam = se3(*tl.T_IMU_CAM[0])
        for row_gt, row_marker in zip(gt.world_from_cam, layout.world_from_marker, strict=True):
            expected = matrix_from_row(row_marker) @ np.linalg.inv(imu_from_marker) @ imu_from_cam
            np.testing.assert_allclose(matrix_from_row(row_gt), expected, atol=1e-12)


def test_ground_truth_on_hand_made_poses(tmp_path: Path, rng: np.random.Generator):
    """Poses checked by hand: marker at the origin, marker == IMU, the camera 10 cm along the
    IMU's x axis, rotated 90° about z: the camera sits at (0.1, 0, 0) facing the same way."""
    layout = tl.write_sequence(tmp_path, rng)
    doc = tl.calibration_json()
    doc["value0"]["T_imu_cam"][0] = tl.pose_json([0.1, 0.0, 0.0], [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)])
    (tmp_path / "camera-calibrationA.json").write_text(json.dumps(doc))
    mocap = tl.mocap_calibration_json()
    mocap["value0"]["T_imu_marker"] = tl.pose_json([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    (tmp_path / "mocap-imu-calibrationA.json").write_text(json.dumps(mocap))
    # The marker moves 1 m along world y, without rotating.
    (layout.seq_dir / "mocap_data.txt").write_text(
        "# mocap poses: time(us) px py pz qx qy qz qw\n0 0 0 0 0 0 0 1\n8333 0 1 0 0 0 0 1\n"
    )
    with load_tumvie(layout.seq_dir) as seq:
        gt = seq.ground_truth
        np.testing.assert_array_equal(gt.t_ns, [0, 8_333_000])
        np.testing.assert_allclose(gt.world_from_cam[:, :3], [[0.1, 0, 0], [0.1, 1, 0]], atol=1e-15)
        np.testing.assert_allclose(np.abs(gt.world_from_cam[:, 3:]), [[0, 0, np.sqrt(0.5), np.sqrt(0.5)]] * 2)


def test_calibration_next_to_the_sequence_and_explicit_paths(tmp_path: Path, rng: np.random.Generator):
    layout = tl.write_sequence(tmp_path, rng, calibration_in_parent=False)
    with load_tumvie(layout.seq_dir) as seq:
        assert seq.calibration.cameras["event_left"].width == 160
    # Explicit files win over whatever lies around.
    elsewhere = tmp_path / "calib"
    elsewhere.mkdir()
    doc = tl.calibration_json()
    doc["value0"]["intrinsics"][0]["intrinsics"]["fx"] = 222.0
    (elsewhere / "mine.json").write_text(json.dumps(doc))
    shutil.move(layout.seq_dir / "mocap-imu-calibrationA.json", elsewhere / "moc.json")
    with load_tumvie(
        layout.seq_dir, calibration=elsewhere / "mine.json", mocap_calibration=elsewhere / "moc.json"
    ) as seq:
        assert seq.calibration.cameras["frame_left"].params[0] == 222.0
        assert seq.ground_truth is not None


def test_calibration_objects_can_be_passed(layout: tl.Layout):
    cam = Camera("pinhole", [100.0, 100.0, 63.5, 47.5], 128, 96)
    ev = Camera("pinhole", [100.0, 100.0, 79.5, 44.5], 160, 90)
    rig = RigCalibration(
        {"frame_left": cam, "frame_right": cam, "event_left": ev, "event_right": ev},
        {k: SE3() for k in CAMERA_KEYS},
    )
    marker = SE3(translation=[0.0, 0.0, 1.0])
    with load_tumvie(layout.seq_dir, calibration=rig, mocap_calibration=marker) as seq:
        assert seq.calibration is rig
        # The camera (== IMU) sits 1 m along the marker's -z axis.
        for row_gt, row_marker in zip(seq.ground_truth.world_from_cam, layout.world_from_marker, strict=True):
            m = matrix_from_row(row_marker)
            np.testing.assert_allclose(row_gt[:3], m[:3, 3] - m[:3, 2], atol=1e-12)


def test_header_lines_without_hash_are_skipped(layout: tl.Layout):
    for side in ("left", "right"):
        path = layout.seq_dir / f"{side}_images/image_timestamps_{side}.txt"
        path.write_text(path.read_text().replace("# timestamps [us]", "timestamp[us]"))
    with load_tumvie(layout.seq_dir) as seq:
        np.testing.assert_array_equal(seq.frames.t_ns, layout.frame_t_ns)


def test_a_sequence_without_mocap_has_no_ground_truth(layout: tl.Layout):
    (layout.seq_dir / "mocap_data.txt").unlink()
    with load_tumvie(layout.seq_dir) as seq:
        assert seq.ground_truth is None
        assert "ground truth none" in repr(seq)


def test_radtan8_and_pinhole_calibrations_map_to_dhptam_models(layout: tl.Layout):
    doc = tl.calibration_json()
    radtan = dict(fx=150.0, fy=151.0, cx=80.0, cy=45.0, k1=0.1, k2=-0.05, p1=0.001, p2=-0.002, k3=0.01)
    doc["value0"]["intrinsics"][2] = {
        "camera_type": "pinhole-radtan8",
        "intrinsics": {**radtan, "k4": 0.0, "k5": 0.0, "k6": 0.0},
    }
    doc["value0"]["intrinsics"][3] = {
        "camera_type": "pinhole",
        "intrinsics": dict(fx=150.0, fy=151.0, cx=80.0, cy=45.0),
    }
    (layout.root / "camera-calibrationA.json").write_text(json.dumps(doc))
    with load_tumvie(layout.seq_dir) as seq:
        left, right = seq.calibration.cameras["event_left"], seq.calibration.cameras["event_right"]
        assert left.model == "radtan" and right.model == "pinhole"
        np.testing.assert_array_equal(
            left.params, [150.0, 151.0, 80.0, 45.0, 0.1, -0.05, 0.001, -0.002, 0.01]
        )


# ---------------------------------------------------------------------------------------------
# corrupt variants: each fails with the documented error, naming the file and the field
# ---------------------------------------------------------------------------------------------


def _rewrite_event(seq: Path, side: str, **changes) -> None:
    """Rewrite one event file with datasets changed or removed (value None)."""
    path = seq / f"{seq.name}-events_{side}.h5"
    with h5py.File(path, "r") as f:
        data = {k: f[f"events/{k}"][:] for k in ("x", "y", "t", "p")}
        index = f["ms_to_idx"][:]
    index = changes.pop("ms_to_idx", index)
    for key, value in changes.items():
        data[key] = value
    with h5py.File(path, "w") as f:
        for key, value in data.items():
            if value is not None:
                f.create_dataset(f"events/{key}", data=value)
        if index is not None:
            f.create_dataset("ms_to_idx", data=index)


def _events_t(seq: Path, side: str = "left") -> np.ndarray:
    with h5py.File(seq / f"{seq.name}-events_{side}.h5", "r") as f:
        return f["events/t"][:]


def _edit_lines(path: Path, edit: Callable[[list[str]], list[str]]) -> None:
    path.write_text("\n".join(edit(path.read_text().splitlines())) + "\n")


def _edit_calibration(root: Path, edit: Callable[[dict], None]) -> None:
    path = root / "camera-calibrationA.json"
    doc = json.loads(path.read_text())
    edit(doc["value0"])
    path.write_text(json.dumps(doc))


def _swap(lines: list[str], i: int, j: int) -> list[str]:
    lines[i], lines[j] = lines[j], lines[i]
    return lines


def _truncate(path: Path, fraction: float) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])


def _scramble_middle(path: Path) -> None:
    """Overwrite the middle of the file (compressed chunk data) with noise."""
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 4096] = np.random.default_rng(7).integers(0, 256, 4096, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))


L = "left_images/image_timestamps_left.txt"
EV = "mocap-desk-events_left.h5"

# (id, edit of the layout, expected error, file name the message must name, field or None)
CORRUPTIONS: list[tuple[str, Callable[[tl.Layout], object], type, str, str | None]] = [
    (
        "missing event file",
        lambda s: (s.seq_dir / "mocap-desk-events_right.h5").unlink(),
        FileError,
        "mocap-desk-events_right.h5",
        None,
    ),
    ("missing timestamps", lambda s: (s.seq_dir / L).unlink(), FileError, "image_timestamps_left.txt", None),
    (
        "missing exposures",
        lambda s: (s.seq_dir / "right_images/image_exposures_right.txt").unlink(),
        FileError,
        "image_exposures_right.txt",
        None,
    ),
    (
        "missing image folder",
        lambda s: shutil.rmtree(s.seq_dir / "right_images"),
        FileError,
        "right_images",
        None,
    ),
    (
        "missing calibration",
        lambda s: (s.root / "camera-calibrationA.json").unlink(),
        FileError,
        "mocap-desk",
        "calibration",
    ),
    (
        "two calibrations",
        lambda s: shutil.copy(s.root / "camera-calibrationA.json", s.root / "camera-calibrationB.json"),
        InputError,
        "camera-calibrationB.json",
        "camera-calibration",
    ),
    (
        "missing mocap calibration",
        lambda s: (s.root / "mocap-imu-calibrationA.json").unlink(),
        FileError,
        "mocap_data.txt",
        "mocap_calibration",
    ),
    (
        "float event times",
        lambda s: _rewrite_event(s.seq_dir, "left", t=_events_t(s.seq_dir).astype(np.float64)),
        ParseError,
        EV,
        "events/t",
    ),
    (
        "float x",
        lambda s: _rewrite_event(s.seq_dir, "left", x=np.zeros(20_000, np.float32)),
        ParseError,
        EV,
        "events/x",
    ),
    ("missing polarity", lambda s: _rewrite_event(s.seq_dir, "left", p=None), ParseError, EV, "events/p"),
    (
        "lengths differ",
        lambda s: _rewrite_event(s.seq_dir, "left", y=np.zeros(19_999, np.uint16)),
        ParseError,
        EV,
        "events",
    ),
    (
        "unsorted event file",
        lambda s: _rewrite_event(s.seq_dir, "left", t=_events_t(s.seq_dir)[::-1].copy(), ms_to_idx=None),
        ParseError,
        EV,
        "events/t",
    ),
    (
        "float ms_to_idx",
        lambda s: _rewrite_event(s.seq_dir, "left", ms_to_idx=np.zeros(10, np.float64)),
        ParseError,
        EV,
        "ms_to_idx",
    ),
    (
        # An index counted from the first event instead of from t = 0 contradicts DSEC.
        "ms_to_idx from another origin",
        lambda s: _rewrite_event(
            s.seq_dir, "left", ms_to_idx=tl.ms_to_idx(_events_t(s.seq_dir) - _events_t(s.seq_dir)[0])
        ),
        ParseError,
        EV,
        "ms_to_idx",
    ),
    (
        "decreasing ms_to_idx",
        lambda s: _rewrite_event(
            s.seq_dir, "left", ms_to_idx=tl.ms_to_idx(_events_t(s.seq_dir))[::-1].copy()
        ),
        ParseError,
        EV,
        "ms_to_idx",
    ),
    ("truncated HDF5", lambda s: _truncate(s.seq_dir / EV, 0.5), FileError, EV, None),
    ("not HDF5 at all", lambda s: (s.seq_dir / EV).write_text("hello"), FileError, EV, None),
    (
        "unsorted frame stamps",
        lambda s: [
            _edit_lines(s.seq_dir / f"{side}_images/image_timestamps_{side}.txt", lambda x: _swap(x, 2, 3))
            for side in ("left", "right")
        ],
        ParseError,
        "image_timestamps_left.txt",
        "image timestamp",
    ),
    (
        "duplicated frame stamps",
        lambda s: _edit_lines(s.seq_dir / L, lambda x: [*x[:3], x[2], *x[4:]]),
        ParseError,
        "image_timestamps_left.txt",
        "image timestamp",
    ),
    (
        "a stamp that is not a number",
        lambda s: _edit_lines(s.seq_dir / L, lambda x: [*x[:2], "12a4", *x[3:]]),
        ParseError,
        "image_timestamps_left.txt",
        "image timestamp",
    ),
    (
        "an image too few",
        lambda s: (s.seq_dir / "left_images/00005.jpg").unlink(),
        InputError,
        "left_images",
        "images",
    ),
    (
        "an exposure too few",
        lambda s: _edit_lines(s.seq_dir / "left_images/image_exposures_left.txt", lambda x: x[:-1]),
        InputError,
        "image_exposures_left.txt",
        "exposure",
    ),
    (
        "stereo counts differ",
        lambda s: [
            (s.seq_dir / "right_images/00005.jpg").unlink(),
            _edit_lines(s.seq_dir / "right_images/image_timestamps_right.txt", lambda x: x[:-1]),
            _edit_lines(s.seq_dir / "right_images/image_exposures_right.txt", lambda x: x[:-1]),
        ],
        InputError,
        "image_timestamps_right.txt",
        "image timestamp",
    ),
    (
        "stereo stamps differ",
        lambda s: _edit_lines(
            s.seq_dir / "right_images/image_timestamps_right.txt", lambda x: [*x[:3], "1725000", *x[4:]]
        ),
        InputError,
        "image_timestamps_right.txt",
        "image timestamp",
    ),
    (
        "unsorted mocap",
        lambda s: _edit_lines(s.seq_dir / "mocap_data.txt", lambda x: _swap(x, 5, 6)),
        ParseError,
        "mocap_data.txt",
        "mocap time",
    ),
    (
        "mocap row too short",
        lambda s: _edit_lines(
            s.seq_dir / "mocap_data.txt", lambda x: [*x[:4], x[4].rsplit(" ", 1)[0], *x[5:]]
        ),
        ParseError,
        "mocap_data.txt",
        "mocap pose",
    ),
    (
        "mocap NaN",
        lambda s: _edit_lines(
            s.seq_dir / "mocap_data.txt", lambda x: [*x[:4], x[4].rsplit(" ", 1)[0] + " nan", *x[5:]]
        ),
        ParseError,
        "mocap_data.txt",
        "pose",
    ),
    (
        "calibration missing a camera",
        lambda s: _edit_calibration(s.root, lambda v: v["intrinsics"].pop()),
        InputError,
        "camera-calibrationA.json",
        "value0.intrinsics",
    ),
    (
        "calibration NaN",
        lambda s: _edit_calibration(
            s.root, lambda v: v["intrinsics"][1]["intrinsics"].update(fx=float("nan"))
        ),
        InputError,
        "camera-calibrationA.json",
        "value0.intrinsics[1].intrinsics.fx",
    ),
    (
        "calibration pose NaN",
        lambda s: _edit_calibration(s.root, lambda v: v["T_imu_cam"][3].update(qw=float("nan"))),
        InputError,
        "camera-calibrationA.json",
        "value0.T_imu_cam[3].qw",
    ),
    (
        "calibration missing k4",
        lambda s: _edit_calibration(s.root, lambda v: v["intrinsics"][2]["intrinsics"].pop("k4")),
        ParseError,
        "camera-calibrationA.json",
        "value0.intrinsics[2].intrinsics.k4",
    ),
    (
        "unknown camera model",
        lambda s: _edit_calibration(s.root, lambda v: v["intrinsics"][0].update(camera_type="eucm")),
        InputError,
        "camera-calibrationA.json",
        "value0.intrinsics[0].camera_type",
    ),
    (
        "rational radtan8",
        lambda s: _edit_calibration(
            s.root,
            lambda v: v["intrinsics"][0].update(
                camera_type="pinhole-radtan8",
                intrinsics=dict(
                    fx=1.0, fy=1.0, cx=0.0, cy=0.0, k1=0, k2=0, p1=0, p2=0, k3=0, k4=0.1, k5=0, k6=0
                ),
            ),
        ),
        InputError,
        "camera-calibrationA.json",
        "value0.intrinsics[0].intrinsics",
    ),
    (
        "bad resolution",
        lambda s: _edit_calibration(s.root, lambda v: v["resolution"].__setitem__(2, [160])),
        ParseError,
        "camera-calibrationA.json",
        "value0.resolution[2]",
    ),
    (
        "calibration not JSON",
        lambda s: (s.root / "camera-calibrationA.json").write_text("{ value0: "),
        ParseError,
        "camera-calibrationA.json",
        None,
    ),
    (
        "mocap calibration without T_imu_marker",
        lambda s: (s.root / "mocap-imu-calibrationA.json").write_text('{"value0": {"T_mocap_world": {}}}'),
        ParseError,
        "mocap-imu-calibrationA.json",
        "value0.T_imu_marker",
    ),
]


@pytest.mark.parametrize(
    ("edit", "error", "names", "field"), [c[1:] for c in CORRUPTIONS], ids=[c[0] for c in CORRUPTIONS]
)
def test_corrupt_input_fails_with_the_documented_error(layout: tl.Layout, edit, error, names, field):
    edit(layout)
    with pytest.raises(error) as info:
        load_tumvie(layout.seq_dir).close()
    err = info.value
    assert type(err) is error  # the documented class itself, never a wrapped h5py/json exception
    assert names in str(err)
    assert err.path is not None and Path(err.path).name in str(err)
    if field is not None:
        assert err.field == field
    # No raw traceback from a library: the chain is cut at the boundary.
    assert err.__suppress_context__ or err.__context__ is None


def test_corrupt_chunk_data_is_a_file_error(layout: tl.Layout):
    """A file whose compressed chunks are garbage fails with a FileError naming it, whether the
    damage is met when the file is opened (first/last time, index check) or by a window read."""
    path = layout.seq_dir / EV
    _scramble_middle(path)

    def read_everything() -> None:
        with load_tumvie(layout.seq_dir) as seq:
            source = seq.events["left"]
            source.window(*source.t_range_ns)

    with pytest.raises(FileError) as info:
        read_everything()
    assert EV in str(info.value) and info.value.path == str(path)
    assert info.value.__suppress_context__


def test_unsorted_events_inside_a_window_are_reported(layout: tl.Layout):
    t = _events_t(layout.seq_dir).copy()
    t[100], t[101] = t[101] + 1, t[100]
    _rewrite_event(layout.seq_dir, "left", t=t, ms_to_idx=None)
    with load_tumvie(layout.seq_dir) as seq:
        with pytest.raises(ParseError, match="not sorted") as info:
            seq.events["left"].window(*seq.events["left"].t_range_ns)
        assert info.value.field == "events/t"


def test_unreadable_and_wrongly_sized_images_fail_on_access(layout: tl.Layout):
    (layout.seq_dir / "left_images/00002.jpg").write_bytes(b"not a jpeg")
    cv2.imwrite(str(layout.seq_dir / "right_images/00003.jpg"), np.zeros((10, 10), np.uint8))
    with load_tumvie(layout.seq_dir) as seq:
        seq.frames[1]  # the others still load
        with pytest.raises(FileError, match=r"00002\.jpg") as info:
            seq.frames[2]
        assert info.value.field == "image"
        with pytest.raises(InputError, match=r"00003\.jpg.*128x96") as info:
            seq.frames[3]
        assert info.value.field == "resolution"


def test_missing_sequence_folder(tmp_path: Path):
    with pytest.raises(FileError, match="sequence folder not found"):
        load_tumvie(tmp_path / "nope")

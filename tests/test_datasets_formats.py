"""VECtor (folder and ROS bag), MVSEC, EuRoC readers and Kalibr import, on fixtures written in
the real layouts by tests/dataset_layouts.py."""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from dataset_layouts import (
    BAD_EVENT,
    BODY_FROM_CAM0,
    CAM0_FROM,
    D,
    K,
    kalibr_camchain,
    matrix_from_row,
    write_euroc,
    write_mvsec,
    write_vector,
    write_vector_bag,
    write_vector_calibration,
)

from dhptam.datasets import (
    EventSource,
    EventStream,
    load,
    load_mvsec,
    load_vector,
    read_kalibr_camchain,
    rig_from_kalibr,
)
from dhptam.datasets.mvsec import MvsecEventSource
from dhptam.datasets.rosbag import BagEventStream, load_vector_bag
from dhptam.errors import FileError, InputError, ParseError


def truth_window(ev: dict[str, np.ndarray], offset_us: int, t0: int, t1: int) -> dict[str, np.ndarray]:
    t_ns = (ev["t"] + offset_us) * 1000
    sel = (t_ns >= t0) & (t_ns < t1)
    return {"x": ev["x"][sel], "y": ev["y"][sel], "t_ns": t_ns[sel], "p": ev["p"][sel].astype(np.int8)}


def assert_window(window: object, want: dict[str, np.ndarray]) -> None:
    for key in ("x", "y", "t_ns", "p"):
        np.testing.assert_array_equal(getattr(window, key), want[key], err_msg=key)


def assert_poses(rows: np.ndarray, mats: list[np.ndarray]) -> None:
    assert len(rows) == len(mats)
    for row, m in zip(rows, mats, strict=True):
        np.testing.assert_allclose(matrix_from_row(row), m, atol=1e-9)


@pytest.fixture
def vector(tmp_path: Path, rng: np.random.Generator):  # type: ignore[no-untyped-def]
    return write_vector(tmp_path / "corner_slow1", rng)


# -- VECtor folder ----------------------------------------------------------------------------------


def test_vector_events_frames_and_ground_truth(vector) -> None:  # type: ignore[no-untyped-def]
    # The fixture really uses zstd (HDF5 filter 32015), as VECtor ships.
    with h5py.File(vector.folder / f"{vector.name}.synced.left_event.hdf5") as f:
        assert "32015" in f["events/t"]._filters
    with load_vector(vector.folder) as seq:
        assert isinstance(seq.events["left"], EventSource)
        assert isinstance(seq.events["left"], EventStream)
        off = vector.t_offset_us
        t0 = (off + 300_000) * 1000 + 500
        t1 = (off + 1_250_000) * 1000
        for side in ("left", "right"):
            assert_window(seq.events[side].window(t0, t1), truth_window(vector.events[side], off, t0, t1))
            assert len(seq.events[side]) == len(vector.events[side]["t"])
        # Frames: start of exposure and exposure exactly from decimal seconds.
        assert len(seq.frames) == 10
        assert seq.frames.t_ns[0] == (off + 50_000) * 1000
        assert np.all(seq.frames.exposure_ns == 3_250_500)
        pair = seq.frames[3]
        np.testing.assert_array_equal(pair.left, vector.images["left"][3])
        np.testing.assert_array_equal(pair.right, vector.images["right"][3])
        # Calibration: plumb-bob → radtan with OpenCV order, joint extrinsics in cam0's frame.
        cam = seq.calibration.cameras["event_left"]
        assert cam.model == "radtan"
        np.testing.assert_allclose(cam.params, [*K[2], *D[2]])
        np.testing.assert_allclose(
            seq.calibration.cam_from_cam("frame_left", "event_right").matrix(), CAM0_FROM[3], atol=1e-9
        )
        # Body-frame chain: world_from_cam = world_from_body · body_from_cam0 (cam0 = frame_left).
        gt = seq.ground_truth
        assert gt is not None
        np.testing.assert_array_equal(gt.t_ns, vector.gt_t_ns)
        assert_poses(gt.world_from_cam, [m @ BODY_FROM_CAM0 for m in vector.world_from_body])


def test_vector_camera_order_moves_the_ground_truth(vector) -> None:  # type: ignore[no-untyped-def]
    # With cam1 declared the left frame camera, the chain picks up cam0_from_cam1.
    order = ("frame_right", "frame_left", "event_left", "event_right")
    with load_vector(vector.folder, camera_order=order) as seq:
        assert seq.ground_truth is not None
        want = [m @ BODY_FROM_CAM0 @ CAM0_FROM[1] for m in vector.world_from_body]
        assert_poses(seq.ground_truth.world_from_cam, want)


def test_vector_missing_extrinsics_entry_names_file_and_field(vector) -> None:  # type: ignore[no-untyped-def]
    calib = vector.folder / "calibration"
    shutil.rmtree(calib)
    write_vector_calibration(calib, drop_cam=2)
    with pytest.raises(ParseError, match=r"cam2\.T_cam0_cam2 is missing") as err:
        load_vector(vector.folder)
    assert err.value.field == "cam2.T_cam0_cam2"
    assert err.value.path is not None and err.value.path.endswith("joint_camera_extrinsic_results.yaml")


def test_vector_bad_distortion_model_and_missing_body(vector) -> None:  # type: ignore[no-untyped-def]
    calib = vector.folder / "calibration"
    (calib / "camera_body_extrinsic_results.yaml").unlink()
    with pytest.raises(FileError, match="T_body_cam0"):
        load_vector(vector.folder)
    path = calib / "left_event_camera_intrinsic_results.yaml"
    path.write_text(path.read_text().replace("plumb_bob", "equidistant"))
    with pytest.raises(InputError, match="distortion_model 'equidistant'") as err:
        load_vector(vector.folder)
    assert err.value.path == str(path)


def test_vector_frame_count_and_timestamp_errors(vector) -> None:  # type: ignore[no-untyped-def]
    ts = vector.folder / f"{vector.name}.synced.right_camera" / "timestamp.txt"
    lines = ts.read_text().splitlines()
    lines[5] = lines[5].split()[0] + " 12.5"  # ends before it starts
    ts.write_text("\n".join(lines) + "\n")
    with pytest.raises(ParseError, match="exposure ends before it starts") as err:
        load_vector(vector.folder)
    assert err.value.line == 6
    (vector.folder / f"{vector.name}.synced.left_camera" / "000004.png").unlink()
    with pytest.raises(InputError, match="9 PNG images"):
        load_vector(vector.folder)


def test_vector_event_file_with_wrong_layout_names_file_and_field(vector) -> None:  # type: ignore[no-untyped-def]
    path = vector.folder / f"{vector.name}.synced.left_event.hdf5"
    with h5py.File(path, "a") as f:
        t = f["events/t"][:]
        del f["events/t"]
        f.create_dataset("events/t", data=t.astype(np.float64) * 1e-6)  # seconds, not µs
    with pytest.raises(ParseError, match="/events/t has dtype float64") as err:
        load_vector(vector.folder)
    assert err.value.path == str(path) and err.value.field == "events/t"


def _flat(m: np.ndarray) -> str:
    """A 4x4 matrix as one flat row-major YAML list, as the VECtor release writes them."""
    return "[" + ", ".join(repr(float(v)) for v in np.asarray(m).ravel()) + "]"


def _as_release_layout(vector) -> Path:  # type: ignore[no-untyped-def]
    """Rearrange the fixture into the VECtor release's layout (names, flat matrices, calibration
    in ``0_calib/`` beside the sequence folders, frames named by time); returns ``0_calib``."""
    calib = vector.folder.parent / "0_calib"
    shutil.move(vector.folder / "calibration", calib)
    for old in calib.glob("*joint*extrinsic*.yaml"):
        old.unlink()
    (calib / "camera_body_extrinsic_results.yaml").unlink()
    small = "".join(f"cam{n}:\n  T_cam0_cam{n}: {_flat(CAM0_FROM[n])}\n" for n in range(4))
    (calib / "small_scale_joint_camera_extrinsic_results.yaml").write_text(small)
    # The large-scale rig is another set-up: cam1 sits elsewhere.
    large = small.replace(_flat(CAM0_FROM[1]), _flat(CAM0_FROM[3]))
    (calib / "large_scale_joint_camera_extrinsic_results.yaml").write_text(large)
    (calib / "camera_mocap_extrinsic_results1.yaml").write_text(
        "cam0:\n"
        f"  T_body_cam: {_flat(BODY_FROM_CAM0)}\n"
        f"  T_cam_body: {_flat(np.linalg.inv(BODY_FROM_CAM0))}\n"
    )
    for side in ("left", "right"):
        folder = vector.folder / f"{vector.name}.synced.{side}_camera"
        for k, start in enumerate(vector.frame_start_s):
            (folder / f"{k:06d}.png").rename(folder / f"{start}.png")
    return calib


def test_vector_release_layout_and_file_names(vector) -> None:  # type: ignore[no-untyped-def]
    calib = _as_release_layout(vector)
    # Two joint extrinsics files in 0_calib: the error names both and the way to choose.
    with pytest.raises(FileError, match=r"small_scale_joint.*joint_extrinsics=") as err:
        load_vector(vector.folder)
    assert err.value.path == str(calib) and "large_scale_joint" in str(err.value)
    small = calib / "small_scale_joint_camera_extrinsic_results.yaml"
    with load_vector(vector.folder, joint_extrinsics=small) as seq:
        np.testing.assert_allclose(
            seq.calibration.cam_from_cam("frame_left", "frame_right").matrix(), CAM0_FROM[1], atol=1e-9
        )
        # Frames named by their time come in time order.
        np.testing.assert_array_equal(seq.frames[0].left, vector.images["left"][0])
        np.testing.assert_array_equal(seq.frames[9].right, vector.images["right"][9])
        gt = seq.ground_truth
        assert gt is not None
        assert_poses(gt.world_from_cam, [m @ BODY_FROM_CAM0 for m in vector.world_from_body])
    # Only T_cam_body (body_from_cam0's inverse) in the mocap file gives the same chain.
    (calib / "large_scale_joint_camera_extrinsic_results.yaml").unlink()
    mocap = calib / "camera_mocap_extrinsic_results1.yaml"
    mocap.write_text(f"cam0:\n  T_cam_body: {_flat(np.linalg.inv(BODY_FROM_CAM0))}\n")
    with load_vector(vector.folder) as seq:
        assert seq.ground_truth is not None
        assert_poses(seq.ground_truth.world_from_cam, [m @ BODY_FROM_CAM0 for m in vector.world_from_body])
    # Missing calibration entries name the file and the field.
    mocap.write_text("cam0:\n  T_cam_imu: [1, 0]\n")
    with pytest.raises(ParseError, match="neither T_body_cam nor T_cam_body") as err:
        load_vector(vector.folder)
    assert err.value.path == str(mocap) and err.value.field == "cam0.T_body_cam"
    mocap.write_text(f"cam0:\n  T_body_cam: {_flat(BODY_FROM_CAM0)[:-6]}]\n")  # 15 numbers
    with pytest.raises(ParseError, match=r"cam0\.T_body_cam must be a 4x4 matrix") as err:
        load_vector(vector.folder)
    assert err.value.field == "cam0.T_body_cam"
    (calib / "camera_mocap_extrinsic_results2.yaml").write_text(mocap.read_text())
    with pytest.raises(FileError, match=r"several camera-body calibrations .*results1.*results2") as err:
        load_vector(vector.folder)
    assert err.value.field == "T_body_cam0"


@pytest.mark.parametrize(
    ("key", "field"),
    [
        ("image_width", "image_width"),
        ("camera_matrix", "camera_matrix"),
        ("distortion_model", "distortion_model"),
        ("distortion_coefficients", "distortion_coefficients"),
    ],
)
def test_vector_missing_intrinsics_entries_name_file_and_field(vector, key: str, field: str) -> None:  # type: ignore[no-untyped-def]
    path = vector.folder / "calibration" / "right_event_camera_intrinsic_results.yaml"
    doc = yaml.safe_load(path.read_text())
    del doc[key]
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ParseError, match=key) as err:
        load_vector(vector.folder)
    assert err.value.path == str(path) and err.value.field == field


def test_an_unavailable_hdf5_filter_names_the_file_the_dataset_and_the_filter(vector) -> None:  # type: ignore[no-untyped-def]
    """VECtor's events are zstd-compressed: without the zstd plugin the reader says so up front
    (file, dataset, filter) instead of failing on the first window with HDF5's message."""
    import hdf5plugin

    path = vector.folder / f"{vector.name}.synced.left_event.hdf5"
    h5py.h5z.unregister_filter(hdf5plugin.ZSTD_ID)
    try:
        assert not h5py.h5z.filter_avail(hdf5plugin.ZSTD_ID)
        with pytest.raises(FileError, match=r"HDF5 filter 32015 \(.*zstd.*\), which is not available") as err:
            load_vector(vector.folder)
        assert err.value.path == str(path) and err.value.field == "events/x"
        with pytest.raises(FileError, match="filter 32015") as err:
            EventSource(path)
        assert err.value.field == "events/x"
    finally:
        hdf5plugin.register("zstd", force=True)
    with EventSource(path) as source:
        assert len(source) == len(vector.events["left"]["t"])


def test_mvsec_events_with_an_unavailable_filter_are_refused(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    import hdf5plugin

    truth = write_mvsec(tmp_path, rng)  # events Blosc-compressed, as the fixture writes them
    h5py.h5z.unregister_filter(hdf5plugin.BLOSC_ID)
    try:
        with pytest.raises(FileError, match=f"filter {hdf5plugin.BLOSC_ID}") as err:
            load_mvsec(tmp_path)
        assert err.value.path == str(truth.data) and err.value.field == "davis/left/events"
    finally:
        hdf5plugin.register("blosc", force=True)
    with load_mvsec(tmp_path) as seq:
        assert len(seq.events["left"]) == len(truth.events["left"])


# -- VECtor bag -----------------------------------------------------------------------------------------


def test_vector_bag_matches_the_truth(vector, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    bag = tmp_path / "corner_slow1.synced.merged.bag"
    write_vector_bag(bag, vector)
    with load_vector_bag(bag, calibration=vector.folder / "calibration") as seq:
        stream = seq.events["right"]
        assert isinstance(stream, BagEventStream) and isinstance(stream, EventStream)
        off = vector.t_offset_us
        assert len(stream) == len(vector.events["right"]["t"])
        for a_us, b_us in ((0, 10), (123_456, 987_001), (1_500_000, 3_000_000), (-5, 1)):
            t0, t1 = (off + a_us) * 1000, (off + b_us) * 1000 + 1
            assert_window(stream.window(t0, t1), truth_window(vector.events["right"], off, t0, t1))
        total = sum(len(w) for w in stream.iter_windows(70_000_000))
        assert total == len(stream)
        i0, i1 = stream.index_range((off + 400_000) * 1000, (off + 800_000) * 1000)
        assert_window(
            stream.slice(i0, i1),
            truth_window(vector.events["right"], off, (off + 400_000) * 1000, (off + 800_000) * 1000),
        )
        assert len(seq.frames) == 10
        np.testing.assert_array_equal(seq.frames[7].left, vector.images["left"][7])
        np.testing.assert_array_equal(seq.frames[7].right, vector.images["right"][7])
        assert seq.frames.t_ns[0] == (off + 50_000) * 1000
        assert seq.ground_truth is not None
        assert_poses(seq.ground_truth.world_from_cam, [m @ BODY_FROM_CAM0 for m in vector.world_from_body])
    # The generic entry point finds the calibration folder beside the bag.
    shutil.copytree(vector.folder / "calibration", tmp_path / "calibration")
    with load("vector-bag", bag) as seq:
        assert len(seq.events["left"]) == len(vector.events["left"]["t"])


def test_vector_bag_missing_topic_and_bad_definition(vector, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    calib = vector.folder / "calibration"
    bag = tmp_path / "a.bag"
    write_vector_bag(bag, vector, skip_topics=("/prophesee/left/events",))
    with pytest.raises(ParseError, match="topic /prophesee/left/events is missing") as err:
        load_vector_bag(bag, calibration=calib)
    assert err.value.path == str(bag) and err.value.field == "/prophesee/left/events"
    bad = tmp_path / "b.bag"
    write_vector_bag(bad, vector, event_def=BAD_EVENT, per_message=5000)
    with pytest.raises(ParseError, match="int32") as err:
        load_vector_bag(bad, calibration=calib)
    assert err.value.field == "/prophesee/left/events.events"


def test_unindexed_bag_is_refused_with_the_file_named(vector, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    bag = tmp_path / "c.bag"
    write_vector_bag(bag, vector, compress=False)
    raw = bytearray(bag.read_bytes())
    at = raw.index(b"index_pos=") + len(b"index_pos=")
    raw[at : at + 8] = bytes(8)  # what a recording cut before `rosbag record` wrote its index looks like
    bag.write_bytes(bytes(raw))
    with pytest.raises(FileError, match=r"not indexed.*rosbag reindex") as err:
        load_vector_bag(bag, calibration=vector.folder / "calibration")
    assert err.value.path == str(bag) and err.value.field == "index"


# -- MVSEC ------------------------------------------------------------------------------------------------


def test_mvsec_units_polarity_pairing_and_pose(tmp_path: Path, rng: np.random.Generator) -> None:
    truth = write_mvsec(tmp_path, rng)
    with load("mvsec", tmp_path) as seq:
        left = seq.events["left"]
        assert isinstance(left, MvsecEventSource) and isinstance(left, EventStream)
        ev = truth.events["left"]
        t_ns = np.rint(ev[:, 2] * 1e6).astype(np.int64) * 1000
        t0, t1 = int(t_ns[1000]), int(t_ns[9000])
        w = left.window(t0, t1)
        sel = (t_ns >= t0) & (t_ns < t1)
        np.testing.assert_array_equal(w.t_ns, t_ns[sel])
        np.testing.assert_array_equal(w.x, ev[sel, 0].astype(np.uint16))
        np.testing.assert_array_equal(w.p, (ev[sel, 3] > 0).astype(np.int8))
        assert set(np.unique(w.p)) == {0, 1}
        # Stamps are seconds of Unix time: rounded to the microsecond, in ns.
        assert seq.frames.t_ns[0] == round(truth.image_ts["left"][0] * 1e6) * 1000
        assert len(seq.frames) == 12  # right frames 7 µs later still pair
        np.testing.assert_array_equal(seq.frames[5].right, truth.images["right"][5])
        assert seq.ground_truth is not None
        assert_poses(seq.ground_truth.world_from_cam, list(truth.poses))
        # A DAVIS: frame and event cameras are one; Kalibr's equidistant is kb4.
        assert seq.calibration.cameras["event_left"].model == "kb4"
        np.testing.assert_allclose(
            seq.calibration.cam_from_cam("frame_right", "frame_left").matrix(),
            np.linalg.inv(CAM0_FROM[1]),
            atol=1e-9,
        )


def test_mvsec_bad_polarity_and_missing_dataset(tmp_path: Path, rng: np.random.Generator) -> None:
    truth = write_mvsec(tmp_path, rng)
    with h5py.File(truth.data, "a") as f:
        d = f["davis/right/events"]
        d[10, 3] = 0.0
        del f["davis/left/image_raw_ts"]
    with pytest.raises(ParseError, match="image_raw_ts is missing") as err:
        load_mvsec(truth.data)
    assert err.value.field == "davis/left/image_raw_ts"
    stream = MvsecEventSource(truth.data, "right")
    with stream, pytest.raises(ParseError, match="-1/\\+1"):
        stream.slice(0, 100)


# -- EuRoC --------------------------------------------------------------------------------------------------


def test_euroc_frames_and_ground_truth(tmp_path: Path, rng: np.random.Generator) -> None:
    truth = write_euroc(tmp_path / "MH_01_easy", rng)
    with load("euroc", tmp_path / "MH_01_easy") as seq:
        assert seq.events == {}
        np.testing.assert_array_equal(seq.frames.t_ns, truth["t"])
        np.testing.assert_array_equal(seq.frames[2].right, truth["images"]["right"][2])
        # T_BS is body_from_cam; the rig frame is the body.
        np.testing.assert_allclose(
            seq.calibration.imu_from_cam["frame_left"].matrix(), BODY_FROM_CAM0, atol=1e-9
        )
        assert seq.ground_truth is not None
        assert_poses(seq.ground_truth.world_from_cam, [m @ BODY_FROM_CAM0 for m in truth["world_from_body"]])
    with pytest.raises(InputError, match="carry their calibration"):
        load("euroc", tmp_path / "MH_01_easy", calibration="x.yaml")


def test_load_rejects_an_unknown_format(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="unknown sequence format 'rosbag2'") as err:
        load("rosbag2", tmp_path)
    assert err.value.field == "format"


# -- Kalibr ---------------------------------------------------------------------------------------


def test_kalibr_conventions(tmp_path: Path) -> None:
    path = tmp_path / "camchain-imucam.yaml"
    path.write_text(kalibr_camchain(with_imu=True, model="radtan"))
    chain = read_kalibr_camchain(path)
    cam0 = chain["cam0"].camera
    assert cam0.model == "radtan"
    # Kalibr radtan [k1, k2, r1, r2] → OpenCV [k1, k2, p1, p2, k3 = 0].
    np.testing.assert_allclose(cam0.params, [*K[0], -0.048, 0.012, -0.024, 0.008, 0.0])
    assert chain["cam0"].cam_from_previous_cam is None and chain["cam0"].rostopic == "/davis/left/image_raw"
    rig, _ = rig_from_kalibr(path)
    # With T_cam_imu the rig frame is the IMU (here the body): imu_from_cam = inverse(T_cam_imu).
    np.testing.assert_allclose(rig.imu_from_cam["frame_left"].matrix(), BODY_FROM_CAM0, atol=1e-9)
    np.testing.assert_allclose(
        rig.imu_from_cam["frame_right"].matrix(), BODY_FROM_CAM0 @ CAM0_FROM[1], atol=1e-9
    )
    # Without it, T_cn_cnm1 (cam1_from_cam0) places cam1 in cam0's frame: the same relative pose.
    path.write_text(kalibr_camchain(with_imu=False))
    rig2, _ = rig_from_kalibr(path)
    np.testing.assert_allclose(rig2.imu_from_cam["frame_left"].matrix(), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(rig2.imu_from_cam["frame_right"].matrix(), CAM0_FROM[1], atol=1e-9)
    assert rig2.cameras["frame_left"].model == "kb4"


def test_kalibr_errors_name_the_field(tmp_path: Path) -> None:
    path = tmp_path / "camchain.yaml"
    path.write_text(kalibr_camchain(with_imu=False).replace("T_cn_cnm1", "T_other"))
    with pytest.raises(ParseError, match=r"cam1\.T_cn_cnm1 is missing") as err:
        rig_from_kalibr(path)
    assert err.value.field == "cam1.T_cn_cnm1"
    path.write_text(kalibr_camchain().replace("camera_model: pinhole", "camera_model: omni", 1))
    with pytest.raises(InputError, match=r"cam0\.camera_model 'omni'"):
        read_kalibr_camchain(path)
    path.write_text(kalibr_camchain().replace("cam0:", "cam5:"))
    with pytest.raises(ParseError, match="missing cam0"):
        read_kalibr_camchain(path)
    path.write_text("cam0: [unclosed\n")
    with pytest.raises(ParseError, match="invalid YAML") as err:
        read_kalibr_camchain(path)
    assert err.value.path == str(path)


def test_run_accepts_the_new_formats(tmp_path: Path, rng: np.random.Generator) -> None:
    from dhptam.cli import build_parser
    from dhptam.run import run

    parser = build_parser()
    for fmt in ("vector", "vector-bag", "mvsec", "euroc"):
        args = parser.parse_args(["run", "--format", fmt, "--sequence", "s", "--out", "o"])
        assert args.format == fmt
    write_euroc(tmp_path / "V1_01", rng)
    with pytest.raises(InputError, match="has no events; run it with mode 'frames'") as err:
        run(tmp_path / "V1_01", tmp_path / "out", fmt="euroc", mode="fusion", progress=False)
    assert err.value.field == "mode"
    # The frames mode reads EuRoC end to end (random images: tracking is lost, frames are read).
    result = run(
        tmp_path / "V1_01", tmp_path / "out", fmt="euroc", mode="frames", progress=False, max_frames=4
    )
    assert result.frames == 4 and (tmp_path / "out" / "trajectory.tum").exists()


def test_run_writes_kitti_and_euroc_trajectories(sim_tiny: Path, tmp_path: Path) -> None:
    from evo.tools import file_interface as evo_fi

    from dhptam.run import run

    out = tmp_path / "out"
    result = run(
        sim_tiny, out, mode="frames", progress=False, threaded=False, trajectory_formats=("kitti", "euroc")
    )
    assert result.tracked > 0
    # The KITTI and EuRoC copies hold the poses of the TUM file (evo reads all three).
    for key in ("trajectory_frame_left", "keyframes"):
        tum = evo_fi.read_tum_trajectory_file(str(out / f"{key}.tum"))
        euroc = evo_fi.read_euroc_csv_trajectory(str(out / f"{key}.csv"))
        kitti = evo_fi.read_kitti_poses_file(str(out / f"{key}.kitti"))
        assert tum.num_poses == euroc.num_poses == kitti.num_poses > 0
        np.testing.assert_allclose(np.stack(euroc.poses_se3), np.stack(tum.poses_se3), atol=1e-8)
        np.testing.assert_allclose(np.stack(kitti.poses_se3), np.stack(tum.poses_se3), atol=1e-8)
        np.testing.assert_allclose(euroc.timestamps, tum.timestamps, atol=1e-9)
    with pytest.raises(InputError, match="unknown trajectory format 'ply'"):
        run(
            sim_tiny,
            tmp_path / "o2",
            mode="frames",
            progress=False,
            max_frames=1,
            trajectory_formats=("ply",),
        )


def test_lower_bound_with_and_without_galloping_hint(rng: np.random.Generator) -> None:
    from dhptam.datasets._common import lower_bound

    for _ in range(500):
        n = int(rng.integers(0, 20000))
        a = np.sort(rng.integers(0, 1000, n))
        v, lo = int(rng.integers(-5, 1005)), int(rng.integers(0, n + 1))
        hint = int(rng.integers(0, 30000)) if rng.random() < 0.8 else None
        got = lower_bound(a.__getitem__, n, v, lo, block=int(rng.integers(1, 64)), hint=hint)
        after = np.nonzero(a[lo:] >= v)[0]
        assert got == (lo + int(after[0]) if after.size else n), (n, v, lo, hint)

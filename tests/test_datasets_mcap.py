"""MCAP logs (dhptam.datasets.mcap): lossless round trips, Foxglove compatibility checked with
the reference Python ``mcap`` reader and Foxglove's own protobuf classes, and clear errors on
damaged logs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from dhptam import SE3, Camera
from dhptam.datasets import CAMERA_KEYS, RigCalibration, TumVieWriter, load_tumvie
from dhptam.datasets.mcap import load_mcap, write_sequence
from dhptam.errors import ParseError


def _assert_sequences_equal(a, b) -> None:  # type: ignore[no-untyped-def]
    assert a.name == b.name
    for key in CAMERA_KEYS:
        ca, cb = a.calibration.cameras[key], b.calibration.cameras[key]
        assert (ca.model, list(ca.params), ca.width, ca.height) == (
            cb.model,
            list(cb.params),
            cb.width,
            cb.height,
        )
        np.testing.assert_array_equal(
            a.calibration.imu_from_cam[key].matrix(), b.calibration.imu_from_cam[key].matrix()
        )
    if a.imu_from_marker is None:
        assert b.imu_from_marker is None
    else:
        np.testing.assert_array_equal(a.imu_from_marker.matrix(), b.imu_from_marker.matrix())
    np.testing.assert_array_equal(a.frames.t_ns, b.frames.t_ns)
    np.testing.assert_array_equal(a.frames.exposure_ns, b.frames.exposure_ns)
    for i in range(len(a.frames)):
        fa, fb = a.frames[i], b.frames[i]
        np.testing.assert_array_equal(fa.left, fb.left)
        np.testing.assert_array_equal(fa.right, fb.right)
        assert fb.left.dtype == np.uint8
    assert set(a.events) == set(b.events)
    for side in a.events:
        ea, eb = a.events[side], b.events[side]
        assert len(ea) == len(eb) and ea.t_range_ns == eb.t_range_ns
        wa, wb = ea.slice(0, len(ea)), eb.slice(0, len(eb))
        for col in ("x", "y", "t_ns", "p"):
            np.testing.assert_array_equal(getattr(wa, col), getattr(wb, col))
            assert getattr(wa, col).dtype == getattr(wb, col).dtype
    if a.ground_truth is None:
        assert b.ground_truth is None
    else:
        np.testing.assert_array_equal(a.ground_truth.t_ns, b.ground_truth.t_ns)
        np.testing.assert_array_equal(a.ground_truth.world_from_cam, b.ground_truth.world_from_cam)


def test_a_simulated_sequence_round_trips_without_loss(sim_tiny: Path, tmp_path: Path) -> None:
    log = tmp_path / "tiny.mcap"
    with load_tumvie(sim_tiny) as seq:
        assert write_sequence(seq, log, progress=False) == log
        with load_mcap(log) as back:
            assert len(back.frames) > 0 and len(back.events["left"]) > 1000
            assert back.ground_truth is not None
            _assert_sequences_equal(seq, back)
            # Time windows and index ranges agree with the HDF5 reader at arbitrary bounds.
            src, dst = seq.events["left"], back.events["left"]
            lo, hi = src.t_range_ns
            for t0, t1 in [(lo, lo + 1), (lo + 12_345, lo + 40_000_000), (hi - 1, hi + 5), (lo - 10, lo)]:
                assert src.index_range(t0, t1) == dst.index_range(t0, t1)
                np.testing.assert_array_equal(src.window(t0, t1).t_ns, dst.window(t0, t1).t_ns)
            step = 33_000_000
            for wa, wb in zip(src.iter_windows(step), dst.iter_windows(step), strict=True):
                np.testing.assert_array_equal(wa.x, wb.x)


def _hand_made(root: Path) -> Path:
    """A hand-made sequence: distinct cameras and extrinsics, events at repeated timestamps."""
    cams = {
        "frame_left": Camera("kb4", [100.0, 101.0, 31.5, 23.5, 0.01, -0.02, 0.003, 0.0004], 64, 48),
        "frame_right": Camera("kb4", [99.0, 98.5, 32.0, 24.0, 0.0, 0.0, 0.0, 0.0], 64, 48),
        "event_left": Camera("pinhole", [80.0, 80.0, 15.5, 11.5], 32, 24),
        "event_right": Camera("radtan", [81.0, 79.0, 16.0, 12.0, 0.1, -0.05, 0.001, 0.002], 32, 24),
    }
    poses = {k: SE3.exp([0.1 * i, -0.02, 0.03, 0.01, 0.2 * i, -0.1]) for i, k in enumerate(CAMERA_KEYS)}
    rig = RigCalibration(cams, poses)
    rng = np.random.default_rng(7)
    with TumVieWriter(root, "hand", rig, SE3.exp([0.0, 0.1, 0.0, 0.3, 0.0, 0.0])) as w:
        for k in range(4):
            t = 10_000_000 + k * 50_000_000
            w.add_frame_pair(
                t,
                2_000_000 + k,
                rng.integers(0, 256, (48, 64), np.uint8),
                rng.integers(0, 256, (48, 64), np.uint8),
            )
        for side in ("left", "right"):
            n = 5000
            t_us = np.sort(rng.integers(5_000, 200_000, n))
            w.add_events(
                side, rng.integers(0, 32, n), rng.integers(0, 24, n), t_us * 1000, rng.integers(0, 2, n)
            )
        rows = ["# mocap poses: time(us) px py pz qx qy qz qw"]
        for k in range(20):
            q = np.array([0.1, -0.2, 0.05 * k, 1.0])
            q /= np.linalg.norm(q)
            rows.append(" ".join(str(v) for v in (8_000 + 10_000 * k, 0.1 * k, -0.5, 1.25, *q)))
        w.add_text_file("mocap_data.txt", "\n".join(rows) + "\n")
    return root / "hand"


def test_a_time_slice_keeps_exactly_its_frames_events_and_poses(tmp_path: Path) -> None:
    with load_tumvie(_hand_made(tmp_path)) as seq:
        log = write_sequence(seq, tmp_path / "slice.mcap", start_s=0.05, duration_s=0.1, progress=False)
        t_first = min(int(seq.frames.t_ns[0]), *(s.t_range_ns[0] for s in seq.events.values()))
        t0, t1 = t_first + 50_000_000, t_first + 150_000_000
        with load_mcap(log) as back:
            keep = (seq.frames.t_ns >= t0) & (seq.frames.t_ns < t1)
            np.testing.assert_array_equal(back.frames.t_ns, seq.frames.t_ns[keep])
            np.testing.assert_array_equal(back.frames.exposure_ns, seq.frames.exposure_ns[keep])
            for side in ("left", "right"):
                expected = seq.events[side].window(t0, t1)
                got = back.events[side].slice(0, len(back.events[side]))
                np.testing.assert_array_equal(got.t_ns, expected.t_ns)
                np.testing.assert_array_equal(got.p, expected.p)
            assert back.calibration.cameras["event_right"].model == "radtan"


def test_the_log_opens_with_the_python_mcap_reader_and_decodes_as_foxglove(tmp_path: Path) -> None:
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    with load_tumvie(_hand_made(tmp_path)) as seq:
        log = write_sequence(seq, tmp_path / "fox.mcap", progress=False)
        expected_schema = {
            "/events/left": "dhptam.EventBatch",
            "/events/right": "dhptam.EventBatch",
            "/frames/left": "foxglove.RawImage",
            "/frames/right": "foxglove.RawImage",
            "/ground_truth": "foxglove.PoseInFrame",
            **{f"/calibration/{k}": "foxglove.CameraCalibration" for k in CAMERA_KEYS},
        }
        with open(log, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            assert summary is not None and summary.chunk_indexes, "log must be chunked and indexed"
            assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
            channels = {c.topic: c for c in summary.channels.values()}
            assert set(channels) == set(expected_schema)
            for topic, channel in channels.items():
                schema = summary.schemas[channel.schema_id]
                assert (schema.name, schema.encoding, channel.message_encoding) == (
                    expected_schema[topic],
                    "protobuf",
                    "protobuf",
                )
            batch_schema = summary.schemas[channels["/events/left"].schema_id]
            fds = descriptor_pb2.FileDescriptorSet.FromString(batch_schema.data)
            pool = descriptor_pool.DescriptorPool()
            for file in fds.file:
                pool.Add(file)
            EventBatch = message_factory.GetMessageClass(pool.FindMessageTypeByName("dhptam.EventBatch"))

            images, events, calibrations, poses = [], [], {}, []
            for _, channel, message in reader.iter_messages():
                if channel.topic == "/frames/left":
                    images.append(RawImage.FromString(message.data))
                elif channel.topic == "/events/left":
                    events.append(EventBatch.FromString(message.data))
                elif channel.topic.startswith("/calibration/"):
                    calibrations[channel.topic] = CameraCalibration.FromString(message.data)
                elif channel.topic == "/ground_truth":
                    poses.append(PoseInFrame.FromString(message.data))

        first = seq.frames[0]
        assert (images[0].width, images[0].height, images[0].encoding, images[0].frame_id) == (
            64,
            48,
            "mono8",
            "frame_left",
        )
        assert images[0].timestamp.ToNanoseconds() == first.t_ns
        np.testing.assert_array_equal(np.frombuffer(images[0].data, np.uint8).reshape(48, 64), first.left)
        cal = calibrations["/calibration/frame_left"]
        assert cal.distortion_model == "kannala_brandt"
        assert list(cal.K) == [100.0, 0.0, 31.5, 0.0, 101.0, 23.5, 0.0, 0.0, 1.0]
        assert list(cal.D) == [0.01, -0.02, 0.003, 0.0004]
        t = np.concatenate([np.frombuffer(b.t_ns, "<i8") for b in events])
        np.testing.assert_array_equal(t, seq.events["left"].slice(0, len(seq.events["left"])).t_ns)
        assert sum(b.count for b in events) == len(seq.events["left"])
        gt = seq.ground_truth
        assert gt is not None and len(poses) == len(gt)
        assert poses[1].pose.orientation.w == gt.world_from_cam[1, 6]
        assert poses[1].pose.position.x == gt.world_from_cam[1, 0]


def _log(tmp_path: Path) -> Path:
    with load_tumvie(_hand_made(tmp_path)) as seq:
        return write_sequence(seq, tmp_path / "good.mcap", progress=False)


def test_a_truncated_log_names_the_file(tmp_path: Path) -> None:
    good = _log(tmp_path)
    bad = tmp_path / "truncated.mcap"
    bad.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ParseError, match=r"truncated\.mcap: magic") as info:
        load_mcap(bad)
    assert info.value.path == str(bad) and info.value.field == "magic"


def test_a_file_that_is_not_mcap_names_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "wrong.mcap"
    data = bytearray(_log(tmp_path).read_bytes())
    data[1:5] = b"HDF5"
    bad.write_bytes(bytes(data))
    with pytest.raises(ParseError, match=r"wrong\.mcap: magic: not an MCAP file"):
        load_mcap(bad)


def test_a_missing_channel_names_the_file_and_the_channel(tmp_path: Path) -> None:
    from dhptam._core import McapReader, McapWriter

    good = _log(tmp_path)
    reader = McapReader(good)
    # Copy everything but the right events into a new log.
    partial = tmp_path / "partial.mcap"
    w = McapWriter(partial)
    x, y, t, p = reader.event_slice("/events/left", 0, reader.event_count("/events/left"))
    w.add_events("/events/left", "event_left", x, y, t, p)
    for side in ("left", "right"):
        topic = f"/frames/{side}"
        for t_ns, frame_id, image in reader.images(topic, 0, reader.topics()[topic]["message_count"]):
            w.add_image(topic, frame_id, t_ns, image)
    w.add_metadata("dhptam.sequence", reader.metadata("dhptam.sequence") or {})
    w.finish()
    with pytest.raises(ParseError, match=r"partial\.mcap: /events/right: channel is missing") as info:
        load_mcap(partial)
    assert info.value.field == "/events/right"


def test_a_log_without_sequence_metadata_is_refused(tmp_path: Path) -> None:
    from dhptam._core import McapWriter

    path = tmp_path / "bare.mcap"
    w = McapWriter(path)
    w.add_events(
        "/events/left",
        "event_left",
        np.zeros(1, np.uint16),
        np.zeros(1, np.uint16),
        np.ones(1, np.int64),
        np.zeros(1, np.int8),
    )
    w.finish()
    with pytest.raises(ParseError, match=r"bare\.mcap: metadata record 'dhptam\.sequence' is missing"):
        load_mcap(path)


def test_a_failed_write_leaves_no_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with load_tumvie(_hand_made(tmp_path)) as seq:
        target = tmp_path / "out.mcap"

        def broken(index: int) -> None:
            raise OSError("disk image unreadable")

        monkeypatch.setattr(type(seq.frames), "__getitem__", lambda self, i: broken(i))
        with pytest.raises(OSError, match="disk image unreadable"):
            write_sequence(seq, target, progress=False)
    assert not target.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith("out.mcap")]


def test_run_record_holds_the_inputs_and_outputs_of_the_run(sim_desk_run: Path, tmp_path: Path) -> None:
    from dhptam._core import McapReader
    from dhptam.cli import main
    from dhptam.trajectory import read_tum

    out, record = tmp_path / "run", tmp_path / "run.mcap"
    args = ["run", "--sequence", str(sim_desk_run), "--out", str(out), "--max-frames", "4", "-q", "--sync"]
    assert main([*args, "--record", str(record), "--record-frames", "png"]) == 0
    t_tum, _ = read_tum(out / "trajectory_frame_left.tum")
    reader = McapReader(record)
    topics = reader.topics()
    assert topics["/slam/world_from_frame_left"]["schema_name"] == "foxglove.PoseInFrame"
    assert topics["/slam/map"]["schema_name"] == "foxglove.PointCloud"
    assert topics["/frames/left"]["schema_name"] == "foxglove.CompressedImage"  # --record-frames png
    t_rec, _, _ = reader.poses("/slam/world_from_frame_left")
    assert len(t_rec) == len(t_tum) == 4
    ((_, frame, points),) = reader.point_clouds("/slam/map")
    assert frame == "world" and points.shape[1] == 3
    # The inputs read back as a sequence: the first four frames and their events, unchanged.
    with load_tumvie(sim_desk_run) as seq, load_mcap(record) as back:
        assert len(back.frames) == 4
        np.testing.assert_array_equal(back.frames.t_ns, seq.frames.t_ns[:4])
        np.testing.assert_array_equal(back.frames[3].left, seq.frames[3].left)
        t_end = int(seq.frames.t_mid_ns[3])
        for side in ("left", "right"):
            expected = seq.events[side].window(seq.events[side].t_range_ns[0], t_end)
            got = back.events[side].slice(0, len(back.events[side]))
            np.testing.assert_array_equal(got.t_ns, expected.t_ns)
            np.testing.assert_array_equal(got.x, expected.x)


# -- frames as PNG (foxglove.CompressedImage) ---------------------------------------------------


def test_png_frames_round_trip_and_decode_as_foxglove_compressed_images(tmp_path: Path) -> None:
    import cv2
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from google.protobuf import descriptor_pb2, descriptor_pool

    with load_tumvie(_hand_made(tmp_path)) as seq:
        raw = write_sequence(seq, tmp_path / "raw.mcap", progress=False)
        png = write_sequence(seq, tmp_path / "png.mcap", progress=False, frame_format="png")
        with load_mcap(png) as back:
            _assert_sequences_equal(seq, back)  # lossless: every pixel, event and pose
        with load_mcap(raw) as back:
            _assert_sequences_equal(seq, back)
        with open(png, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            assert summary is not None
            channel = next(c for c in summary.channels.values() if c.topic == "/frames/right")
            schema = summary.schemas[channel.schema_id]
            assert (schema.name, schema.encoding) == ("foxglove.CompressedImage", "protobuf")
            # Our descriptor matches Foxglove's own field for field.
            pool = descriptor_pool.DescriptorPool()
            for file in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
                pool.Add(file)
            ours = pool.FindMessageTypeByName("foxglove.CompressedImage")
            theirs = CompressedImage.DESCRIPTOR
            assert {(f.name, f.number, f.type) for f in ours.fields} == {
                (f.name, f.number, f.type) for f in theirs.fields
            }
            images = [
                CompressedImage.FromString(m.data)
                for _, c, m in reader.iter_messages()
                if c.topic == "/frames/right"
            ]
        assert len(images) == len(seq.frames)
        assert (images[2].format, images[2].frame_id) == ("png", "frame_right")
        assert images[2].timestamp.ToNanoseconds() == seq.frames.t_ns[2]
        decoded = cv2.imdecode(np.frombuffer(images[2].data, np.uint8), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(decoded, seq.frames[2].right)


def test_an_unknown_frame_format_is_refused(tmp_path: Path) -> None:
    from dhptam.datasets.mcap import McapRecorder
    from dhptam.errors import InputError

    with load_tumvie(_hand_made(tmp_path)) as seq:
        with pytest.raises(InputError, match="frame_format must be one of raw, png") as err:
            write_sequence(seq, tmp_path / "x.mcap", progress=False, frame_format="jpeg")
        assert err.value.field == "frame_format"
        with pytest.raises(InputError, match="frame_format"):
            McapRecorder(tmp_path / "y.mcap", seq, frame_format="webp")
    assert not list(tmp_path.glob("*.mcap*"))


def _copy(
    src: Path,
    dst: Path,
    *,
    metadata: dict[str, str] | None = None,
    frames: str = "raw",
    right_frames: object = None,
) -> Path:
    """Copy a log written by write_sequence, optionally with other metadata, or with the right
    frames replaced by ``right_frames(writer, t_ns)``."""
    from dhptam._core import McapReader, McapWriter

    reader = McapReader(src)
    w = McapWriter(dst)
    for side in ("left", "right"):
        topic = f"/events/{side}"
        w.add_events(topic, f"event_{side}", *reader.event_slice(topic, 0, reader.event_count(topic)))
    for side in ("left", "right"):
        topic = f"/frames/{side}"
        for t_ns, frame_id, image in reader.images(topic, 0, reader.topics()[topic]["message_count"]):
            if side == "right" and callable(right_frames):
                right_frames(w, t_ns)
            else:
                w.add_image(topic, frame_id, t_ns, image)
    meta = reader.metadata("dhptam.sequence")
    assert meta is not None
    w.add_metadata("dhptam.sequence", meta if metadata is None else metadata)
    w.finish()
    return dst


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda m: m.pop("cameras"), "dhptam.sequence.cameras"),
        (lambda m: m.pop("exposure_ns"), "dhptam.sequence.exposure_ns"),
        (
            lambda m: m.update(cameras=m["cameras"].replace('"event_right"', '"event_rigth"')),
            "dhptam.sequence.cameras.event_right",
        ),
        (
            lambda m: m.update(imu_from_cam=m["imu_from_cam"].replace('"frame_left"', '"left"')),
            "dhptam.sequence.imu_from_cam.frame_left",
        ),
        (lambda m: m.update(cameras=m["cameras"][:-2]), "dhptam.sequence.cameras"),
    ],
)
def test_missing_calibration_entries_name_the_file_and_the_field(tmp_path: Path, edit, field: str) -> None:  # type: ignore[no-untyped-def]
    from dhptam._core import McapReader

    good = _log(tmp_path)
    meta = McapReader(good).metadata("dhptam.sequence")
    assert meta is not None
    edit(meta)
    bad = _copy(good, tmp_path / "bad.mcap", metadata=meta)
    with pytest.raises(ParseError, match=r"bad\.mcap: metadata dhptam\.sequence") as err:
        load_mcap(bad)
    assert err.value.path == str(bad) and err.value.field == field


def test_an_unknown_chunk_compression_names_the_file_and_the_channel(tmp_path: Path) -> None:
    with load_tumvie(_hand_made(tmp_path)) as seq:
        good = write_sequence(seq, tmp_path / "lz4.mcap", progress=False, compression="lz4")
    # Rename the compression of every chunk (and chunk index) to one no reader knows.
    data = good.read_bytes()
    needle = b"\x03\x00\x00\x00lz4"
    assert data.count(needle) >= 2
    bad = tmp_path / "lz9.mcap"
    bad.write_bytes(data.replace(needle, b"\x03\x00\x00\x00lz9"))
    with pytest.raises(ParseError, match=r"lz9\.mcap: /events/\w+: .*lz9") as err:
        load_mcap(bad)
    assert err.value.path == str(bad) and err.value.field in ("/events/left", "/events/right")


def test_frames_of_another_schema_or_undecodable_png_are_refused(tmp_path: Path) -> None:
    good = _log(tmp_path)

    def poses(w, t_ns: int) -> None:  # type: ignore[no-untyped-def]
        w.add_poses("/frames/right", "world", np.array([t_ns]), np.array([[0.0, 0, 0, 0, 0, 0, 1]]))

    wrong = _copy(good, tmp_path / "wrong.mcap", right_frames=poses)
    with pytest.raises(ParseError, match=r"/frames/right carries 'foxglove\.PoseInFrame'") as err:
        load_mcap(wrong)
    assert err.value.field == "/frames/right"

    def garbage(w, t_ns: int) -> None:  # type: ignore[no-untyped-def]
        w.add_compressed_image("/frames/right", "frame_right", t_ns, b"\x89PNG not really", "png")

    broken = _copy(good, tmp_path / "broken.mcap", right_frames=garbage)
    with load_mcap(broken) as seq:
        with pytest.raises(ParseError, match=r"/frames/right frame 1: .* do not decode") as err:
            seq.frames[1]
        assert err.value.path == str(broken) and err.value.field == "/frames/right"

"""Trajectory writers read back by evo, and ``dhptam convert`` (VECtor/MVSEC/bag → TUM-VIE)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from dataset_layouts import (
    BODY_FROM_CAM0,
    matrix_from_row,
    transform,
    write_mvsec,
    write_vector,
    write_vector_bag,
)

from dhptam.cli import main
from dhptam.convert import convert
from dhptam.datasets import load_tumvie
from dhptam.errors import FileError, InputError
from dhptam.trajectory import TRAJECTORY_FORMATS, write_euroc, write_kitti, write_trajectory, write_tum

evo_fi = pytest.importorskip("evo.tools.file_interface", reason="evo is a dev dependency")


def poses(n: int) -> tuple[np.ndarray, np.ndarray]:
    t_ns = 1_403_636_579_000_000_000 + 33_333_333 * np.arange(n, dtype=np.int64) + 7
    mats = np.stack(
        [transform([0.1, 1.0, 0.3 * k], 0.2 * k, [0.5 * k, -0.1 * k, 0.02 * k * k]) for k in range(n)]
    )
    return t_ns, mats


def test_evo_reads_every_trajectory_format(tmp_path: Path) -> None:
    t_ns, mats = poses(7)
    write_tum(tmp_path / "a.tum", t_ns, mats)
    write_kitti(tmp_path / "a.kitti", mats)
    write_euroc(tmp_path / "a.csv", t_ns, mats)
    tum = evo_fi.read_tum_trajectory_file(str(tmp_path / "a.tum"))
    kitti = evo_fi.read_kitti_poses_file(str(tmp_path / "a.kitti"))
    euroc = evo_fi.read_euroc_csv_trajectory(str(tmp_path / "a.csv"))
    for traj in (tum, kitti, euroc):
        np.testing.assert_allclose(np.stack(traj.poses_se3), mats, atol=1e-8)
    # evo holds times as float seconds: compare at its resolution.
    np.testing.assert_allclose(tum.timestamps, t_ns / 1e9, rtol=0, atol=1e-6)
    np.testing.assert_allclose(euroc.timestamps, t_ns / 1e9, rtol=0, atol=1e-6)
    # EuRoC puts w first: the column after z is qw.
    first = (tmp_path / "a.csv").read_text().splitlines()[2].split(",")
    assert first[0] == str(t_ns[1])
    np.testing.assert_allclose(
        float(first[4]), evo_fi.read_tum_trajectory_file(str(tmp_path / "a.tum")).orientations_quat_wxyz[1][0]
    )


def test_write_trajectory_dispatch_and_errors(tmp_path: Path) -> None:
    t_ns, mats = poses(3)
    for fmt in TRAJECTORY_FORMATS:
        write_trajectory(tmp_path / f"k.{fmt}", fmt, t_ns, mats)
    assert len((tmp_path / "k.kitti").read_text().splitlines()) == 3
    with pytest.raises(InputError, match="unknown trajectory format 'g2o'"):
        write_trajectory(tmp_path / "x", "g2o", t_ns, mats)
    with pytest.raises(InputError, match="increase strictly"):
        write_trajectory(tmp_path / "x.kitti", "kitti", t_ns[::-1].copy(), mats)
    assert not (tmp_path / "x.kitti").exists()


def test_convert_vector_window_to_tumvie(tmp_path: Path, rng: np.random.Generator) -> None:
    truth = write_vector(tmp_path / "seq", rng)
    dst = tmp_path / "out" / "seq_tumvie"
    convert(truth.folder, dst, from_format="vector", start_s=0.2, duration_s=0.45)
    off = truth.t_offset_us
    t0 = (off + 50_000 + 200_000) * 1000  # first frame + start
    t1 = t0 + 450_000_000
    with load_tumvie(dst) as seq:
        # Frames 2..6 start inside [t0, t1); their exposures survive exactly.
        np.testing.assert_array_equal(seq.frames.t_ns, (off + 50_000 + 100_000 * np.arange(2, 7)) * 1000)
        assert np.all(seq.frames.exposure_ns == 3_250_500)
        for side in ("left", "right"):
            ev = truth.events[side]
            t_ns = (ev["t"] + off) * 1000
            sel = (t_ns >= t0) & (t_ns < t1)
            w = seq.events[side].window(0, 2**62)
            np.testing.assert_array_equal(w.t_ns, t_ns[sel])
            np.testing.assert_array_equal(w.x, ev["x"][sel])
            np.testing.assert_array_equal(w.p, ev["p"][sel].astype(np.int8))
        gt = seq.ground_truth
        assert gt is not None
        keep = (truth.gt_t_ns >= t0) & (truth.gt_t_ns < t1)
        np.testing.assert_array_equal(gt.t_ns, truth.gt_t_ns[keep])
        want = [m @ BODY_FROM_CAM0 for m, k in zip(truth.world_from_body, keep, strict=True) if k]
        for row, m in zip(gt.world_from_cam, want, strict=True):
            np.testing.assert_allclose(matrix_from_row(row), m, atol=1e-9)
        cam = seq.calibration.cameras["frame_right"]
        assert cam.model == "radtan"
    # Nothing but the result is left in the output folder (atomic output).
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["seq_tumvie"]


def test_convert_cli_from_bag_and_mvsec(
    tmp_path: Path, rng: np.random.Generator, capsys: pytest.CaptureFixture[str]
) -> None:
    truth = write_vector(tmp_path / "seq", rng, n_events=4000)
    bag = tmp_path / "seq.bag"
    write_vector_bag(bag, truth, per_message=700)
    dst = tmp_path / "from_bag"
    calib = str(truth.folder / "calibration")
    assert (
        main(
            [
                "convert",
                "--from",
                "vector-bag",
                "--to",
                "tum-vie",
                str(bag),
                str(dst),
                "--calibration",
                calib,
                "-q",
            ]
        )
        == 0
    )
    assert capsys.readouterr().out.strip() == str(dst)
    with load_tumvie(dst) as seq:
        # The window starts at the first frame (50 ms after the first events).
        assert len(seq.events["left"]) == int(np.count_nonzero(truth.events["left"]["t"] >= 50_000))
        assert len(seq.frames) == 10
    mv = write_mvsec(tmp_path / "mvsec", rng)
    with pytest.raises(InputError, match="already exists"):
        convert(mv.data, dst, from_format="mvsec")
    convert(mv.data, tmp_path / "mv_out", from_format="mvsec", duration_s=0.3)
    with load_tumvie(tmp_path / "mv_out") as seq:
        assert len(seq.frames) == 6  # 50 ms frames in [0, 0.3 s)


def test_convert_failure_leaves_nothing(tmp_path: Path, rng: np.random.Generator) -> None:
    truth = write_vector(tmp_path / "seq", rng, n_events=2000)
    (truth.folder / f"{truth.name}.synced.right_camera" / "000005.png").write_bytes(b"not a png")
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(FileError, match=r"000005\.png"):
        convert(truth.folder, out / "x", from_format="vector", progress=True)
    assert list(out.iterdir()) == []


def test_convert_to_mcap_and_back_keeps_the_same_window(tmp_path: Path, rng: np.random.Generator) -> None:
    """VECtor → MCAP (a time window) → TUM-VIE gives what VECtor → TUM-VIE gives directly."""
    truth = write_vector(tmp_path / "seq", rng)
    direct = tmp_path / "direct"
    convert(truth.folder, direct, from_format="vector", start_s=0.2, duration_s=0.45)
    log = tmp_path / "seq.mcap"
    assert (
        main(
            [
                *("convert", "--from", "vector", "--to", "mcap", str(truth.folder), str(log)),
                *("--start", "0.2", "--duration", "0.45", "-q"),
            ]
        )
        == 0
    )
    back = tmp_path / "back"
    convert(log, back, from_format="mcap", to_format="tum-vie")
    with load_tumvie(direct) as a, load_tumvie(back) as b:
        np.testing.assert_array_equal(a.frames.t_ns, b.frames.t_ns)
        np.testing.assert_array_equal(a.frames.exposure_ns, b.frames.exposure_ns)
        np.testing.assert_array_equal(a.frames[1].left, b.frames[1].left)
        for side in ("left", "right"):
            wa, wb = a.events[side].window(0, 2**62), b.events[side].window(0, 2**62)
            assert len(wa) > 0
            for field in ("t_ns", "x", "y", "p"):
                np.testing.assert_array_equal(getattr(wa, field), getattr(wb, field))

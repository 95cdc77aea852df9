"""TUM trajectories (dhptam.trajectory) and their evaluation (dhptam.eval, dhptam eval)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dhptam import SE3, SO3
from dhptam.cli import main
from dhptam.errors import ConfigError, FileError, InputError, NumericalError, ParseError
from dhptam.eval import (
    Trajectory,
    coverage,
    errors_by_segment,
    evaluate,
    load_trajectory,
    read_segments,
    read_suite,
    run_suite,
    write_segments,
)
from dhptam.trajectory import read_tum, rows_to_matrices, write_tum

_NS = 1_000_000_000


def _circle(n: int = 40, radius: float = 1.0) -> Trajectory:
    """A camera going once around a horizontal circle, 20 Hz, yawing with the motion."""
    t = np.arange(n, dtype=np.int64) * 50_000_000 + 1_700_000_000 * _NS
    angles = 2 * np.pi * np.arange(n) / n
    rows = np.zeros((n, 7))
    rows[:, 0], rows[:, 1] = radius * np.cos(angles), radius * np.sin(angles)
    rows[:, 2] = 0.3
    for i, a in enumerate(angles):
        rows[i, 3:] = SO3.exp([0.0, 0.0, a]).quat_xyzw()
    return Trajectory(t, rows, "circle")


def test_write_tum_round_trips_exactly_and_evo_reads_it(tmp_path: Path) -> None:
    from evo.tools import file_interface

    ref = _circle()
    path = tmp_path / "sub" / "traj.tum"
    write_tum(path, ref.t_ns, rows_to_matrices(ref.rows))
    t_ns, rows = read_tum(path)
    assert np.array_equal(t_ns, ref.t_ns)  # nanoseconds survive the text file exactly
    # A quaternion and its negative are the same rotation; compare the matrices.
    assert np.allclose(rows_to_matrices(rows), rows_to_matrices(ref.rows), atol=1e-9)
    evo_traj = file_interface.read_tum_trajectory_file(str(path))
    assert np.allclose(evo_traj.timestamps, ref.t_ns / _NS, rtol=0, atol=1e-6)
    assert np.allclose(evo_traj.positions_xyz, ref.rows[:, :3], atol=1e-9)
    assert np.allclose(
        np.abs(np.sum(evo_traj.orientations_quat_wxyz * ref.rows[:, [6, 3, 4, 5]], axis=1)), 1.0
    )
    assert not [p for p in path.parent.iterdir() if p.name != "traj.tum"]  # no temporary left


def test_write_tum_rejects_bad_input(tmp_path: Path) -> None:
    poses = np.tile(np.eye(4), (2, 1, 1))
    with pytest.raises(InputError, match="increase"):
        write_tum(tmp_path / "a.tum", [5, 5], poses)
    with pytest.raises(InputError, match="2 times but 3 poses"):
        write_tum(tmp_path / "a.tum", [1, 2], np.tile(np.eye(4), (3, 1, 1)))
    with pytest.raises(InputError, match="shape"):
        write_tum(tmp_path / "a.tum", [1, 2], np.zeros((2, 3)))
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("line", "message", "field"),
    [
        ("1.0 0 0 0 0 0 0", "expected 8 values", "columns"),
        ("1.0 0 0 zero 0 0 0 1", "not a number", "pose"),
        ("one 0 0 0 0 0 0 1", "timestamp", "timestamp"),
        ("1.0 0 0 0 0 0 0 2", "norm", "quaternion"),
        ("0.5 0 0 0 0 0 0 1", "not after the one on line 2", "timestamp"),
    ],
)
def test_bad_tum_lines_are_errors_naming_file_and_line(
    tmp_path: Path, line: str, message: str, field: str
) -> None:
    path = tmp_path / "bad.tum"
    path.write_text("# header\n0.9 0 0 0 0 0 0 1\n" + line + "\n")
    with pytest.raises(ParseError, match=message) as info:
        read_tum(path)
    assert info.value.path == str(path) and info.value.line == 3 and info.value.field == field
    assert f"{path}:3" in str(info.value)


def test_missing_or_empty_files_are_errors(tmp_path: Path) -> None:
    with pytest.raises(FileError, match="not found"):
        read_tum(tmp_path / "none.tum")
    (tmp_path / "empty.tum").write_text("# nothing\n")
    with pytest.raises(ParseError, match="no poses"):
        read_tum(tmp_path / "empty.tum")


def test_perturbed_copy_has_the_known_ate() -> None:
    """Alternating ±d offsets along z on a circle with an even number of poses: they have
    zero mean and no correlation with the positions, so Umeyama leaves the copy where it is
    and the ATE RMSE is exactly d."""
    ref = _circle(40)
    d = 0.02
    rows = ref.rows.copy()
    rows[:, 2] += d * (-1.0) ** np.arange(len(ref))
    result = evaluate(Trajectory(ref.t_ns, rows), ref, align="se3")
    assert result.ate_rmse_m == pytest.approx(d, rel=1e-6)
    assert result.ape["max"] == pytest.approx(d, rel=1e-6)
    assert result.rotation_deg == pytest.approx(0.0, abs=1e-6)
    assert result.coverage == 1.0 and result.poses_matched == 40
    # Consecutive poses move by 2d relative to each other along z.
    assert result.rpe["rmse"] == pytest.approx(2 * d, rel=1e-6)
    assert result.ate_percent_of_path == pytest.approx(100 * d / result.path_length_m)


def test_errors_by_segment_split_the_ate_by_labelled_spans() -> None:
    """The circle's second half is off by ±3 cm along z, the first half exact: split at its
    middle (the second half in two spans of one label) each part gets its own RMSE (the
    whole-run alignment tilts a little towards the noisy half), the two pool back into the
    whole run's; a label without a pose gets NaN."""
    ref = _circle(40)
    rows = ref.rows.copy()
    rows[20:, 2] += 0.03 * (-1.0) ** np.arange(20)
    result = evaluate(Trajectory(ref.t_ns, rows), ref, align="se3")
    t = ref.t_ns
    parts = errors_by_segment(
        result,
        [("first", int(t[0]), int(t[20])), ("second", int(t[20]), int(t[30])),
         ("second", int(t[30]), int(t[-1]) + 1), ("never", 0, 1)],
    )  # fmt: skip
    assert list(parts) == ["first", "second", "never"]
    assert parts["first"].poses == 20 and parts["second"].poses == 20
    assert parts["first"].rmse_m < 0.1 * parts["second"].rmse_m
    assert parts["second"].rmse_m == pytest.approx(0.03, rel=0.05)
    assert np.hypot(parts["first"].rmse_m, parts["second"].rmse_m) / np.sqrt(2) == pytest.approx(
        result.ate_rmse_m, rel=1e-9
    )
    assert parts["never"].poses == 0 and np.isnan(parts["never"].rmse_m)
    with pytest.raises(InputError, match="ends before it starts"):
        errors_by_segment(result, [("backwards", int(t[5]), int(t[1]))])


def test_segments_files_round_trip_and_name_the_bad_line(tmp_path: Path) -> None:
    spans = [("dark", 1_320_000_000, 2_080_000_000), ("bright", 2_920_000_001, 3_280_000_000)]
    write_segments(tmp_path / "spans.csv", spans)
    assert read_segments(tmp_path / "spans.csv") == spans  # exact to the nanosecond
    (tmp_path / "hand.csv").write_text("# my recording\n\nlabel,start_s,end_s\ndark, 1.5 ,2\ndark,3,4.25\n")
    assert read_segments(tmp_path / "hand.csv") == [("dark", 1_500_000_000, 2_000_000_000),
                                                     ("dark", 3_000_000_000, 4_250_000_000)]  # fmt: skip
    for text, line, match in [
        ("dark,1.0\n", 1, "expected 'label,start_s,end_s'"),
        ("label,start_s,end_s\ndark,1.0,soon\n", 2, "end_s must be a number of seconds"),
        ("dark,2.0,1.0\n", 1, "must end after it starts"),
        ("dark,nan,1.0\n", 1, "start_s must be finite"),
        (",1,2\n", 1, "expected 'label,start_s,end_s'"),
    ]:
        (tmp_path / "bad.csv").write_text(text)
        with pytest.raises(ParseError, match=match) as info:
            read_segments(tmp_path / "bad.csv")
        assert info.value.line == line and info.value.path == str(tmp_path / "bad.csv")
    (tmp_path / "empty.csv").write_text("label,start_s,end_s\n# nothing yet\n")
    with pytest.raises(ParseError, match="no span"):
        read_segments(tmp_path / "empty.csv")
    with pytest.raises(FileError, match="not found"):
        read_segments(tmp_path / "missing.csv")
    with pytest.raises(InputError, match="without commas"):
        write_segments(tmp_path / "x.csv", [("a,b", 0, 1)])
    assert not (tmp_path / "x.csv").exists()


def test_se3_alignment_removes_a_rigid_motion_and_sim3_a_scale() -> None:
    ref = _circle(40)
    moved = SE3(SO3.exp([0.2, -0.1, 0.7]), [3.0, -1.0, 0.5])
    scale = 0.37
    m = rows_to_matrices(ref.rows)
    est_rigid = np.einsum("ij,njk->nik", moved.matrix(), m)
    est_scaled = est_rigid.copy()
    est_scaled[:, :3, 3] *= scale
    rigid = evaluate(Trajectory.from_poses(ref.t_ns, est_rigid), ref, align="se3")
    assert rigid.ate_rmse_m < 1e-9 and rigid.scale == 1.0
    wrong = evaluate(Trajectory.from_poses(ref.t_ns, est_scaled), ref, align="se3")
    assert wrong.ate_rmse_m > 0.1
    recovered = evaluate(Trajectory.from_poses(ref.t_ns, est_scaled), ref, align="sim3")
    assert recovered.ate_rmse_m < 1e-9
    assert recovered.scale == pytest.approx(1.0 / scale, rel=1e-9)


def test_reference_is_interpolated_at_estimate_times() -> None:
    ref = _circle(400)  # 20 Hz, 20 s
    est_t = ref.t_ns[10:-10:7] + 13_000_000  # between reference stamps
    from dhptam.eval import interpolate

    rows, ok = interpolate(ref, est_t, max_gap_s=0.1)
    assert ok.all()
    # On the circle the interpolated position stays within the chord's sagitta of the truth.
    angles = 2 * np.pi * ((est_t - ref.t_ns[0]) / 50_000_000) / 400
    truth = np.c_[np.cos(angles), np.sin(angles)]
    assert np.abs(rows[:, :2] - truth).max() < 1e-4
    _, ok_far = interpolate(ref, est_t, max_gap_s=0.01)  # reference samples are 50 ms apart
    assert not ok_far.any()


def test_coverage_counts_the_tracked_part_of_the_reference_span() -> None:
    ref_t = np.arange(0, 101, dtype=np.int64) * 100_000_000  # 0–10 s
    est_t = np.r_[np.arange(0, 31), np.arange(80, 101)].astype(np.int64) * 100_000_000  # lost 3–8 s
    assert coverage(ref_t, est_t) == pytest.approx(0.5)
    assert coverage(ref_t, ref_t) == 1.0
    assert coverage(ref_t, est_t[:1]) == 0.0


def test_too_few_matched_poses_is_an_error() -> None:
    ref = _circle(40)
    late = Trajectory(ref.t_ns + 100 * _NS, ref.rows, "late.tum")
    with pytest.raises(InputError, match=r"late.tum: only 0 of 40"):
        evaluate(late, ref)
    with pytest.raises(InputError, match="align"):
        evaluate(ref, ref, align="se2")
    still = ref.rows.copy()
    still[:, :3] = 0.0  # one point: no scale can be determined
    with pytest.raises(NumericalError, match="sim3 alignment needs estimate positions"):
        evaluate(Trajectory(ref.t_ns, still, "still.tum"), Trajectory(ref.t_ns, still), align="sim3")


def test_positions_on_one_line_are_aligned_by_the_orientations() -> None:
    """A back-and-forth translation: Umeyama cannot fix the rotation about the line, the
    orientations can; a rigidly moved (and for sim3 scaled) copy aligns back exactly, and an
    error along the line is still measured."""
    ref = _circle(40)
    line = ref.rows.copy()
    line[:, 0] = np.sin(np.linspace(0.0, 6.0, len(line)))  # back and forth along x
    line[:, 1:3] = 0.0
    ref_line = Trajectory(ref.t_ns, line, "line.tum")
    moved = SE3(SO3.exp([0.2, -0.1, 0.7]), [3.0, -1.0, 0.5])
    est = np.einsum("ij,njk->nik", moved.matrix(), rows_to_matrices(line))
    rigid = evaluate(Trajectory.from_poses(ref.t_ns, est), ref_line, align="se3")
    assert rigid.aligned_by == "orientations"
    assert rigid.ate_rmse_m < 1e-9
    assert rigid.rotation_deg == pytest.approx(np.degrees(np.linalg.norm([0.2, -0.1, 0.7])), rel=1e-9)
    scaled = est.copy()
    scaled[:, :3, 3] *= 0.37
    sim3 = evaluate(Trajectory.from_poses(ref.t_ns, scaled), ref_line, align="sim3")
    assert sim3.ate_rmse_m < 1e-9 and sim3.scale == pytest.approx(1 / 0.37, rel=1e-9)
    stretched = est.copy()
    stretched[:, :3, 3] += (
        0.05 * (moved.matrix()[:3, :3] @ np.array([1.0, 0.0, 0.0])) * np.sign(line[:, :1])
    )  # 5 cm off along the line, away from the middle
    off = evaluate(Trajectory.from_poses(ref.t_ns, stretched), ref_line, align="se3")
    assert off.aligned_by == "orientations"
    assert 0.03 < off.ate_rmse_m < 0.05
    assert evaluate(ref, ref).aligned_by == "positions"


def test_cli_eval_writes_json_and_plots(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ref = _circle(40)
    rows = ref.rows.copy()
    rows[:, 2] += 0.01 * (-1.0) ** np.arange(40)
    write_tum(tmp_path / "ref.tum", ref.t_ns, ref.rows)
    write_tum(tmp_path / "est.tum", ref.t_ns, rows)
    out = tmp_path / "out"
    code = main(
        [
            "eval",
            "--estimate",
            str(tmp_path / "est.tum"),
            "--reference",
            str(tmp_path / "ref.tum"),
            "--align",
            "se3",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    assert "ATE RMSE 0.0100 m" in capsys.readouterr().out
    doc = json.loads((out / "eval.json").read_text())
    assert doc["ate_rmse_m"] == pytest.approx(0.01, rel=1e-6) and doc["align"] == "se3"
    for name in ("eval_trajectories.png", "eval_errors.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (tmp_path / "broken.tum").write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0\n")
    code = main(
        [
            "eval",
            "--estimate",
            str(tmp_path / "broken.tum"),
            "--reference",
            str(tmp_path / "ref.tum"),
            "--out",
            str(out),
        ]
    )
    assert code == 2
    assert "broken.tum:2" in capsys.readouterr().err


def test_cli_eval_splits_the_error_by_the_segments_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--segments``: each label's ATE RMSE printed and in eval.json (NaN where no pose); a
    bad segments file fails before anything is written."""
    ref = _circle(40)
    rows = ref.rows.copy()
    rows[20:, 2] += 0.01 * (-1.0) ** np.arange(20)
    write_tum(tmp_path / "ref.tum", ref.t_ns, ref.rows)
    write_tum(tmp_path / "est.tum", ref.t_ns, rows)
    write_segments(
        tmp_path / "spans.csv",
        [("calm", int(ref.t_ns[0]), int(ref.t_ns[20])), ("shaky", int(ref.t_ns[20]), int(ref.t_ns[-1]) + 1),
         ("later", int(ref.t_ns[-1]) + _NS, int(ref.t_ns[-1]) + 2 * _NS)],
    )  # fmt: skip
    base = ["eval", "--estimate", str(tmp_path / "est.tum"), "--reference", str(tmp_path / "ref.tum")]
    assert main([*base, "--segments", str(tmp_path / "spans.csv"), "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out
    assert "calm: ATE RMSE" in printed and "over 20 poses" in printed and "later: no pose" in printed
    doc = json.loads((tmp_path / "out" / "eval.json").read_text())
    assert doc["segments"]["calm"]["poses"] == 20 and doc["segments"]["shaky"]["poses"] == 20
    assert doc["segments"]["shaky"]["ate_rmse_m"] == pytest.approx(0.01, rel=0.05)
    assert doc["segments"]["calm"]["ate_rmse_m"] < 0.1 * doc["segments"]["shaky"]["ate_rmse_m"]
    assert np.isnan(doc["segments"]["later"]["ate_rmse_m"])
    (tmp_path / "bad.csv").write_text("calm,0,oops\n")
    assert main([*base, "--segments", str(tmp_path / "bad.csv"), "--out", str(tmp_path / "out2")]) == 2
    assert "bad.csv:1: end_s must be a number of seconds" in capsys.readouterr().err
    assert not (tmp_path / "out2").exists()


def test_suite_gives_a_comparison_table(tmp_path: Path) -> None:
    ref = _circle(40)
    write_tum(tmp_path / "ref.tum", ref.t_ns, ref.rows)
    for name, d in (("good", 0.01), ("bad", 0.05)):
        rows = ref.rows.copy()
        rows[:, 2] += d * (-1.0) ** np.arange(40)
        write_tum(tmp_path / f"{name}.tum", ref.t_ns, rows)
    write_tum(tmp_path / "half.tum", ref.t_ns[:20], ref.rows[:20])
    suite = tmp_path / "suite.toml"
    suite.write_text(
        'align = "se3"\n'
        '[[run]]\nmethod = "fusion"\nsequence = "circle"\nestimate = "good.tum"\nreference = "ref.tum"\n'
        '[[run]]\nmethod = "frames"\nsequence = "circle"\nestimate = "bad.tum"\nreference = "ref.tum"\n'
        '[[run]]\nmethod = "frames"\nsequence = "circle-b"\nestimate = "half.tum"\nreference = "ref.tum"\n'
    )
    table, results = run_suite(suite, tmp_path / "out")
    lines = table.splitlines()
    assert lines[0] == "| method | circle | circle-b |"
    assert lines[2] == "| fusion | 0.010 | – |"
    assert lines[3].startswith("| frames | 0.050 | 0.000 (")  # half the span: coverage shown
    assert results[("frames", "circle-b")].coverage == pytest.approx(19 / 39)
    assert (tmp_path / "out" / "table.md").read_text().endswith(table)
    assert len(json.loads((tmp_path / "out" / "summary.json").read_text())) == 3
    suite.write_text(
        '[[run]]\nmethod = "a"\nsequence = "b"\nestimate = "good.tum"\nreference = "ref.tum"\nscale = 2\n'
    )
    with pytest.raises(ConfigError, match=r"run\[0\] has unknown keys \['scale'\]"):
        read_suite(suite)


def test_tum_vie_mocap_reference_matches_the_camera_ground_truth(sim_tiny: Path) -> None:
    """The simulator writes both the mocap marker poses and the left camera's poses; read
    through the TUM-VIE mocap path with the calibration files, they are the same trajectory."""
    camera_truth = load_trajectory(sim_tiny / "groundtruth_frame_left.txt", "tum")
    mocap = load_trajectory(sim_tiny / "mocap_data.txt", "tum-vie-mocap")
    assert mocap.t_ns[0] == 0 and len(mocap) > 100
    result = evaluate(camera_truth, mocap, align="se3")
    assert result.ate_rmse_m < 1e-5
    assert result.rotation_deg < 1e-3  # no alignment needed: same world frame
    with pytest.raises(InputError, match=r"mocap_data\.txt"):
        load_trajectory(sim_tiny / "groundtruth_frame_left.txt", "tum-vie-mocap")

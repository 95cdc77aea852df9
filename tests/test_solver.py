"""dhptam.solver and ``dhptam solve``: BAL and g2o files written here solve to their known
optimum, arrays round-trip through bundle_adjust, reports carry the documented keys, malformed
files raise ParseError naming the line, the GIL is released during a solve, and one shared
problem is solved as a smoke test (the large ones live in benches/bench_solver.py)."""

from __future__ import annotations

import itertools
import json
import threading
import time

import numpy as np
import pytest
from conftest import shared_path

from dhptam import cli, solver
from dhptam.errors import FileError, InputError, ParseError


def _rotation(w: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(w)
    if theta < 1e-15:
        return np.eye(3)
    k = w / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * kx @ kx


def _project(cam: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The BAL camera model, written independently of the Rust one."""
    p = _rotation(cam[:3]) @ x + cam[3:6]
    p = -p[:2] / p[2]
    r2 = p @ p
    return cam[6] * (1 + cam[7] * r2 + cam[8] * r2 * r2) * p


def _scene(seed: int = 0, n_cam: int = 6, n_pt: int = 40):
    rng = np.random.default_rng(seed)
    cams = []
    for i in range(n_cam):
        a = 2 * np.pi * i / n_cam
        z = np.array([np.cos(a), 0.0, np.sin(a)])
        y = np.array([0.0, 1.0, 0.0])
        rot = np.vstack([np.cross(y, z), y, z])
        # Angle-axis of rot (angle below π here).
        angle = np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1))
        axis = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
        w = axis / (2 * np.sin(angle)) * angle if angle > 1e-9 else np.zeros(3)
        t = -rot @ (10 * z)
        cams.append(np.r_[w, t, 500 + 20 * i, 0.01, 0.001])
    cams = np.array(cams)
    pts = rng.uniform(-2, 2, (n_pt, 3))
    ci, pi, px = [], [], []
    for j in range(n_pt):
        for i in range(n_cam):
            if (i + 2 * j) % 4 != 3:
                ci.append(i)
                pi.append(j)
                px.append(_project(cams[i], pts[j]))
    return cams, pts, np.array(ci), np.array(pi), np.array(px)


def _write_bal(path, cams, pts, ci, pi, px):
    lines = [f"{len(cams)} {len(pts)} {len(px)}"]
    lines += [f"{c} {p} {float(u)!r} {float(v)!r}" for c, p, (u, v) in zip(ci, pi, px, strict=True)]
    lines += [repr(float(v)) for v in np.r_[cams.ravel(), pts.ravel()]]
    path.write_text("\n".join(lines) + "\n")


def test_bundle_adjust_recovers_scene_from_arrays():
    cams, pts, ci, pi, px = _scene()
    rng = np.random.default_rng(1)
    start_pts = pts + rng.normal(0, 0.05, pts.shape)
    start_cams = cams.copy()
    start_cams[2:, 3:6] += rng.normal(0, 0.05, (len(cams) - 2, 3))
    out_cams, out_pts, report = solver.bundle_adjust(
        start_cams, start_pts, ci, pi, px, fixed_cameras=[0, 1], threads=2, max_iterations=100
    )
    assert report.initial_cost > 10.0
    assert report.final_cost < 1e-12
    assert report.threads == 2
    np.testing.assert_allclose(out_pts, pts, atol=1e-6)
    np.testing.assert_allclose(out_cams, cams, atol=1e-5, rtol=1e-6)
    # The inputs are left alone; the history starts at the initial cost and only decreases.
    assert not np.allclose(start_pts, pts, atol=1e-3)
    costs = [c for c, _ in report.history]
    assert costs[0] == report.initial_cost
    assert all(b <= a for a, b in itertools.pairwise(costs))


def test_bal_file_solves_to_known_optimum_and_cli_json(tmp_path, capsys):
    cams, pts, ci, pi, px = _scene(seed=2)
    start = pts + np.random.default_rng(3).normal(0, 0.05, pts.shape)
    path = tmp_path / "problem-6-40-test.txt"
    _write_bal(path, cams, start, ci, pi, px)
    # Initial cost computed here, independently of the solver: ½Σ‖r‖².
    expected = 0.5 * sum(
        float(np.sum((_project(cams[c], start[p]) - x) ** 2)) for c, p, x in zip(ci, pi, px, strict=True)
    )
    out = tmp_path / "solved.txt"
    assert cli.main(["solve", "bal", str(path), "--threads", "2", "--json", "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert set(report) == {"initial_cost", "final_cost", "iterations", "seconds", "threads", "termination"}
    assert report["initial_cost"] == pytest.approx(expected, rel=1e-12)
    # The gauge is free here (no camera fixed), the cost still reaches its zero optimum.
    assert report["final_cost"] < 1e-8 * report["initial_cost"]
    assert report["threads"] == 2
    again = solver.solve_bal(out)
    assert again.initial_cost == pytest.approx(report["final_cost"], rel=1e-6, abs=1e-12)


def test_pose_graph_file_solves_and_writes_optimised_graph(tmp_path, capsys):
    # A square of four planar poses with exact odometry and one loop closure, start bent.
    text = (
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1.2 0.1 1.4\nVERTEX_SE2 2 0.9 1.3 3.0\nVERTEX_SE2 3 -0.2 0.8 -1.7\n"
        "EDGE_SE2 0 1 1 0 1.5707963267948966 10 0 0 10 0 10\n"
        "EDGE_SE2 1 2 1 0 1.5707963267948966 10 0 0 10 0 10\n"
        "EDGE_SE2 2 3 1 0 1.5707963267948966 10 0 0 10 0 10\n"
        "EDGE_SE2 3 0 1 0 1.5707963267948966 10 0 0 10 0 10\n"
    )
    path = tmp_path / "square.g2o"
    path.write_text(text)
    out = tmp_path / "opt.g2o"
    assert cli.main(["solve", "pose-graph", str(path), "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["kind"] == "se2"
    assert (report["vertices"], report["edges"]) == (4, 4)
    assert report["final_cost"] < 1e-12
    poses = {
        int(f[1]): [float(v) for v in f[2:5]]
        for f in (line.split() for line in out.read_text().splitlines())
        if f[0] == "VERTEX_SE2"
    }
    np.testing.assert_allclose(poses[0], [0, 0, 0], atol=1e-12)  # the gauge vertex stays put
    np.testing.assert_allclose(poses[1], [1, 0, np.pi / 2], atol=1e-7)
    np.testing.assert_allclose(poses[2][:2], [1, 1], atol=1e-7)
    np.testing.assert_allclose(poses[3], [0, 1, -np.pi / 2], atol=1e-7)


def test_malformed_files_raise_parse_error_naming_the_line(tmp_path):
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 4 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(ParseError) as info:
        solver.solve_pose_graph(bad)
    assert info.value.line == 3
    assert info.value.path == str(bad)
    assert "not a vertex" in str(info.value)
    bal = tmp_path / "bad.txt"
    bal.write_text("1 1 1\n0 0 1.0 nan\n")
    with pytest.raises(ParseError) as info:
        solver.solve_bal(bal)
    assert info.value.line == 2
    with pytest.raises(FileError):
        solver.solve_bal(tmp_path / "missing.txt")
    assert cli.main(["solve", "bal", str(bal)]) == 2


def test_invalid_arguments_raise_input_error():
    cams, pts, ci, pi, px = _scene()
    with pytest.raises(InputError, match="loss"):
        solver.bundle_adjust(cams, pts, ci, pi, px, loss="l1")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="camera_index"):
        solver.bundle_adjust(cams, pts, ci[:-1], pi, px)
    with pytest.raises(InputError, match="observations"):
        solver.bundle_adjust(cams, pts, ci + 100, pi, px)


def test_solve_releases_the_gil():
    cams, pts, ci, pi, px = _scene(seed=4, n_cam=12, n_pt=1500)
    start = pts + np.random.default_rng(5).normal(0, 0.05, pts.shape)
    ticks = 0
    done = threading.Event()

    def count():
        nonlocal ticks
        while not done.is_set():
            ticks += 1
            time.sleep(0.0005)

    counter = threading.Thread(target=count)
    counter.start()
    try:
        _, _, report = solver.bundle_adjust(
            cams, start, ci, pi, px, fixed_cameras=[0, 1], max_iterations=40, linear_solver="sparse"
        )
    finally:
        done.set()
        counter.join()
    # Python code ran while Rust solved: the counter advanced during the call.
    assert report.seconds > 0.0
    assert ticks >= 3


def test_shared_pose_graph_smoke():
    path = shared_path("data", "posegraph", "input_M3500_g2o.g2o")
    report = solver.solve_pose_graph(path, threads=1)
    assert report.extra["kind"] == "se2"
    assert report.extra["vertices"] == 3500
    # GTSAM's Levenberg-Marquardt ends at 68.957 on this graph (SPEC-NOTES §8).
    assert report.final_cost == pytest.approx(68.957, rel=1e-3)

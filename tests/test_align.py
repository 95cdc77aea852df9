"""δP_align estimation (dhptam.align, ``dhptam calibrate-align``) on simulated sequences."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dhptam import _core
from dhptam.align import calibrate_align, ransac_translation, write_align_config
from dhptam.cli import main
from dhptam.datasets import load_tumvie
from dhptam.errors import NumericalError


def _config(align: tuple[float, float], depth_m: float = 0.0) -> _core.Config:
    return _core.Config.from_toml(
        f"[fusion]\nplane_depth_m = {depth_m}\nalign_px = [{align[0]}, {align[1]}]\n"
    )


def test_simulated_sequence_needs_no_offset(sim_small_desk: Path) -> None:
    """The simulator's calibration is exact, so δP_align is 0: measured (0.04, −0.11) px on
    this sequence; bounded at 0.75 px per axis. Without the SGBM parallax removal the warp at
    infinity leaves a depth-dependent offset of several pixels."""
    with load_tumvie(sim_small_desk) as seq:
        estimate = calibrate_align(seq, _config((0.0, 0.0)))
        assert estimate.matches >= 100 and estimate.inliers >= 30 and estimate.frames_used >= 8
        assert np.all(np.abs(estimate.align_px) < 0.75), estimate
        # The same with the plane at 2 m: the estimate does not depend on the plane depth.
        at_plane = calibrate_align(seq, _config((0.0, 0.0), depth_m=2.0))
        assert np.allclose(at_plane.align_px, estimate.align_px, atol=0.5)
        uncompensated = calibrate_align(seq, _config((0.0, 0.0)), depth_compensation=False)
        assert np.hypot(*uncompensated.align_px) > 1.0


def test_injected_offset_is_measured_and_undone(sim_small_desk: Path) -> None:
    """A wrong δP_align of (1.5, −1.0) px in the configuration is measured as a residual of
    about (−1.5, +1.0) px, so the written value returns near the true 0."""
    with load_tumvie(sim_small_desk) as seq:
        clean = calibrate_align(seq, _config((0.0, 0.0)))
        injected = calibrate_align(seq, _config((1.5, -1.0)))
    assert injected.previous_px == (1.5, -1.0)
    assert np.allclose(np.subtract(injected.residual_px, clean.residual_px), (-1.5, 1.0), atol=0.3), injected
    assert np.all(np.abs(injected.align_px) < 0.75)


def test_cli_writes_align_px_into_the_config(sim_small_desk: Path, tmp_path: Path) -> None:
    base = tmp_path / "base.toml"
    base.write_text("[fusion]\nbeta_max = 0.3\nalign_px = [2.0, 0.0]\n")
    out = tmp_path / "aligned.toml"
    code = main(
        ["calibrate-align", "--sequence", str(sim_small_desk), "--config", str(base), "--out", str(out)]
    )
    assert code == 0
    fusion = _core.Config.from_file(out).to_dict()["fusion"]
    assert fusion["beta_max"] == 0.3  # the rest of the base configuration is kept
    assert np.all(np.abs(fusion["align_px"]) < 0.75)
    assert base.read_text().endswith("align_px = [2.0, 0.0]\n")  # the base is untouched


def test_too_few_matches_and_ransac() -> None:
    offsets = np.array([[0.1, 0.0], [0.0, 0.1], [-0.1, 0.0], [5.0, 5.0], [0.05, -0.05]])
    median, inliers = ransac_translation(offsets, inlier_px=0.5)
    assert inliers.tolist() == [True, True, True, False, True]
    assert np.allclose(median, [0.025, -0.0])
    with pytest.raises(NumericalError, match="no matches"):
        ransac_translation(np.empty((0, 2)))


def test_dark_sequence_without_matches_is_an_error(sim_tiny: Path) -> None:
    with load_tumvie(sim_tiny) as seq, pytest.raises(NumericalError, match="high-confidence"):
        calibrate_align(seq, None, min_matches=10_000)


def test_write_align_config_keeps_everything_else(tmp_path: Path) -> None:
    base = _core.Config.from_toml("[fusion]\nbeta_max = 0.25\n")
    written = write_align_config(base, (0.125, -0.5), tmp_path / "c.toml")
    assert written.to_dict()["fusion"]["align_px"] == [0.125, -0.5]
    assert _core.Config.from_file(tmp_path / "c.toml") == written
    assert written.to_dict()["fusion"]["beta_max"] == 0.25

"""Shared test helpers.

``shared_path`` is the one way tests reach the read-only reference material in ``../shared``
(models, BAL and pose-graph problems, trajectories). It fails, never skips, when the folder
is missing, so a broken checkout cannot pass by running fewer tests.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def shared_path(*parts: str) -> Path:
    """Path of a file under the shared reference folder, which must exist.

    The folder is ``$DHPTAM_SHARED`` when set, else ``shared/`` next to the repository.
    """
    root = Path(os.environ.get("DHPTAM_SHARED", REPO.parent / "shared"))
    path = root.joinpath(*parts)
    if not path.exists():
        pytest.fail(
            f"reference file {path} is missing: these tests need the read-only 'shared' folder "
            f"next to the repository (or DHPTAM_SHARED pointing at it)",
            pytrace=False,
        )
    return path


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded generator, so failures reproduce."""
    return np.random.default_rng(20261126)


# -- simulated sequences for the front-end, depth and eval tests (frontend branch) -------------


@pytest.fixture(scope="session")
def sim_tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The ``tiny`` preset (1 s, 128-pixel frames, HDR lighting: dark and bright segments),
    simulated once per session; the sequence folder (TUM-VIE layout + ground truth)."""
    from dhptam.sim import simulate

    return simulate(tmp_path_factory.mktemp("sim"), preset="tiny", seed=0).path


#: The rest of :func:`sim_tiny_pause`: (start, duration), seconds.
PAUSE_S = (0.4, 0.5)


@pytest.fixture(scope="session")
def sim_tiny_pause(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """1.3 s of the ``tiny-mixed`` preset (128-pixel frames, normal lighting) along the real
    ``ecd_poster_6dof`` trajectory, the camera held still over :data:`PAUSE_S` (``simulate``'s
    ``pause``); simulated once per session (a few seconds)."""
    from dhptam.sim import simulate

    trajectory = str(shared_path("data", "trajectories", "ecd_poster_6dof.csv"))
    folder = tmp_path_factory.mktemp("pause")
    return simulate(folder, preset="tiny-mixed", trajectory=trajectory, duration_s=1.3, pause=PAUSE_S).path


@pytest.fixture(scope="session")
def sim_small_desk(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """0.5 s of the ``desk`` preset (320-pixel frames, normal lighting), simulated once per
    session (about 15 s on two cores): enough events and texture for δP_align matching."""
    from dhptam.sim import simulate

    return simulate(tmp_path_factory.mktemp("sim"), preset="desk", duration_s=0.5, seed=0).path


@pytest.fixture(scope="session")
def sim_desk_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """1.2 s of the ``desk`` preset (normal lighting), long enough for the end-to-end run tests;
    simulated once per session."""
    from dhptam.sim import simulate

    return simulate(tmp_path_factory.mktemp("sim"), preset="desk", duration_s=1.2, seed=1).path

"""The type stub `_core.pyi` matches the compiled module (mypy's stubtest)."""

from __future__ import annotations

import subprocess
import sys


def test_stub_matches_compiled_module():
    result = subprocess.run(
        [sys.executable, "-m", "mypy.stubtest", "dhptam._core", "--ignore-missing-stub"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stdout + result.stderr

"""The README's examples run as written, so the docs cannot drift from the code."""

from __future__ import annotations

import re

import numpy as np
from conftest import REPO
from tumvie_layout import write_sequence


def python_blocks(markdown: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", markdown, flags=re.DOTALL)


def test_readme_python_examples_run(capsys, tmp_path, monkeypatch):
    blocks = python_blocks((REPO / "README.md").read_text(encoding="utf-8"))
    assert blocks, "the README has no Python example"
    # The dataset example reads "data/mocap-desk": give it a real-layout sequence there.
    write_sequence(tmp_path / "data", np.random.default_rng(0), name="mocap-desk", n_frames=12)
    monkeypatch.chdir(tmp_path)
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {})
    # The error-handling example prints the message it documents.
    assert "expected an (N, 3) array" in capsys.readouterr().out

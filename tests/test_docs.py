"""The README's examples run as written, so the docs cannot drift from the code."""

from __future__ import annotations

import re

from conftest import REPO


def python_blocks(markdown: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", markdown, flags=re.DOTALL)


def test_readme_python_examples_run(capsys):
    blocks = python_blocks((REPO / "README.md").read_text(encoding="utf-8"))
    assert blocks, "the README has no Python example"
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {})
    # The error-handling example prints the message it documents.
    assert "expected an (N, 3) array" in capsys.readouterr().out

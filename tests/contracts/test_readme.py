"""The README's Python example runs and prints what the README says."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

README = Path(__file__).resolve().parents[2] / "README.md"


def test_readme_api_example_runs() -> None:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "the README lost its Python example"
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(blocks[0], "README.md", "exec"), {})
    lines = out.getvalue().splitlines()
    assert lines[0] == "True [0.0, 0.0, 1.29]"
    assert lines[1] == "[0.0, 0.0, 1.0]"
    free_mm = float(lines[2].split()[2])
    assert abs(free_mm - 20.0) < 1.5
    assert lines[-1] == "True [0.0, 0.0, 1.29]"  # the fused surface


def test_readme_starts_with_the_two_commands() -> None:
    text = README.read_text()
    assert "bash packaging/bootstrap.sh && bash packaging/test.sh" in text
    ci = (README.parent / ".ci" / "run").read_text()
    assert "bash packaging/bootstrap.sh && bash packaging/test.sh" in ci

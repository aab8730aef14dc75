"""The README's Python example runs as written."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


@pytest.mark.slow
def test_the_readme_python_example_runs():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(encoding="utf-8"), flags=re.S)
    assert len(blocks) == 1, "the README has one Python example"
    scope: dict = {}
    exec(compile(blocks[0], str(README), "exec"), scope)  # noqa: S102 (our own README)
    f, xs = scope["f"], scope["xs"]
    assert tuple(f.shape) == (4, 6) and np.isfinite(f.detach().numpy()).all()
    assert xs.shape[:2] == (100, 100) and np.isfinite(xs.numpy()).all()

"""Shared fixtures of the test suite."""

from __future__ import annotations

import diffcontact  # noqa: F401  (before torch: it sets OpenMP's wait policy, read when torch loads)

# isort: split
import os

import pytest
import torch

if os.environ.get("PYTEST_XDIST_WORKER"):  # (one test process per CPU: one thread each, not one per CPU each)
    torch.set_num_threads(1)


@pytest.fixture
def float64_default():
    """Tensors made without a dtype are float64 inside the test, and the previous default is restored after it
    (never set at import: the default would leak into every module collected later)."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)

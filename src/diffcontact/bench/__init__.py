"""Benchmarks: the solver against its reference, the simulation of the tasks, solver stress tests."""

from __future__ import annotations

from diffcontact.errors import ConfigError


def check_counts(lo: int = 1, **values) -> None:
    """ConfigError naming the first argument (an integer or a list of them) that is empty or has a value that is not
    an integer >= ``lo``: checked before a benchmark prints its header."""
    for name, value in values.items():
        items = list(value) if isinstance(value, (list, tuple)) else [value]
        if not items or any(isinstance(v, bool) or not isinstance(v, int) or v < lo for v in items):
            raise ConfigError(f"{name} = {value!r}: every value must be an integer >= {lo}")

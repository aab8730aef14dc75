"""The peers' parameter search: CMA-ES restarted with a doubled population leaves a basin that one run settles in.

Skipped without the optimiser: ``pip install -e '.[peers]'``."""

from __future__ import annotations

import numpy as np
import pytest

from diffcontact.peers.cube import Param

SPACE = (Param("a", 0.0, 1.0, log=False, nominal=0.2), Param("b", 0.0, 1.0, log=False, nominal=0.2))


def _two_basins(engine, tosses, params, table_height, starts=None) -> dict[str, float]:
    """A wide basin of value 1 around the nominal values, a narrow one of value 0 at (0.85, 0.85)."""
    x = np.array([params["a"], params["b"]])
    return {"objective": float(min(1.0 + np.sum((x - 0.2) ** 2), 50.0 * np.sum((x - 0.85) ** 2)))}


def test_restarts_find_the_narrow_basin_within_the_budget(monkeypatch):
    pytest.importorskip("cma")
    import diffcontact.peers.fit as fit

    monkeypatch.setattr(fit, "score", _two_basins)
    result = fit.fit_parameters(None, None, 0.0, budget=600, seed=0, echo=lambda s: None, space=SPACE)  # type: ignore[arg-type]
    runs = result["optimiser"]["runs"]
    assert runs[0]["start"] == "nominal" and runs[0]["best"] == pytest.approx(1.0, abs=1e-3)  # (the wide basin)
    assert "stalled" in runs[0]["stop"] and [r["popsize"] for r in runs[:2]] == [6, 12]
    assert result["train_metrics"]["objective"] < 0.5  # (the narrow basin: the wide one is 1 at its least)
    assert abs(result["params"]["a"] - 0.85) < 0.1 and abs(result["params"]["b"] - 0.85) < 0.1
    assert result["optimiser"]["evaluations"] <= 600 == result["optimiser"]["budget"]
    assert result["optimiser"]["evaluations"] == sum(r["popsize"] * r["generations"] for r in runs)

"""`diffcontact simulate`: the .npz fields and shapes, recorded config and versions, the GIF, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from diffcontact.cli import app
from diffcontact.errors import ConfigError
from diffcontact.simulate import simulate_task


def test_simulate_writes_npz_and_gif(tmp_path):
    out, gif = tmp_path / "bd.npz", tmp_path / "bd.gif"
    res = CliRunner().invoke(
        app, ["simulate", "BD5", "--n", "3", "--steps", "12", "--seed", "4", "--out", str(out), "--gif", str(gif)]
    )
    assert res.exit_code == 0, res.output
    with np.load(out) as stored:
        data = {k: stored[k] for k in stored.files}
    assert data["x"].shape == (3, 12, 15, 2) and data["v"].shape == (3, 12, 15, 2)
    assert data["t"].shape == (12,) and np.allclose(np.diff(data["t"]), 0.01)
    assert data["energy"].shape == (3, 12) and data["contact"].shape == (3, 12)
    assert data["contact"].dtype == bool and not data["contact"][:, 0].any()
    assert 'name = "BD5"' in str(data["config"])
    meta = json.loads(str(data["meta"]))
    assert meta["seed"] == 4 and meta["torch"] and meta["diffcontact"] and meta["contact_model"] == "CM"
    assert gif.stat().st_size > 1000
    assert not list(tmp_path.glob("*.tmp*")) and sorted(p.name for p in tmp_path.iterdir()) == ["bd.gif", "bd.npz"]
    # the energy column is the true energy of the stored states (g = 0: kinetic only, no drift without impacts)
    free = ~data["contact"].any(1)
    if free.any():
        e = data["energy"][free]
        assert np.allclose(e, e[:, :1], rtol=1e-6)


def test_simulate_same_seed_same_data(tmp_path):
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    simulate_task("CP3", 2, 5, 7, str(a))
    simulate_task("CP3", 2, 5, 7, str(b))
    with np.load(a) as first, np.load(b) as second:
        assert np.array_equal(first["x"], second["x"])


def test_simulate_unknown_task_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="unknown task 'BP9'"):
        simulate_task("BP9", 1, 5, 0, str(tmp_path / "x.npz"))
    assert not (tmp_path / "x.npz").exists()

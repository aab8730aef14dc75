"""`diffcontact spread`: several runs' learned values and evaluations side by side, and the runs it refuses."""

from __future__ import annotations

import json
import statistics

import pytest
from typer.testing import CliRunner

from diffcontact.cli import app
from diffcontact.errors import ConfigError
from diffcontact.eval.spread import spread, spread_table


def _run(path, seed: int, mu: float, com_z: float, model: str = "CM-CD-CLNN", metrics: bool = True):
    path.mkdir(parents=True)
    (path / "config.json").write_text(json.dumps({"args": {"task": "CubeToss", "model": model, "seed": seed}}))
    learned = {
        "mu": {"learned": [mu]},
        "e": {"learned": [0.0]},
        "centre_of_mass": {"learned": [0.0, 0.0, com_z]},
        "g": 9.81,
        "g_learned": False,
        "table_height_m": {"value": -0.0019},
    }
    (path / "learned.json").write_text(json.dumps(learned))
    if metrics:
        (path / "eval").mkdir()
        (path / "eval" / "metrics.json").write_text(json.dumps({"position_error_pct": 10 * mu, "same_final_face": 44}))
    return path


def test_each_value_gets_its_runs_mean_std_and_range(tmp_path):
    mus, coms = [0.17, 0.174, 0.18], [0.006, 0.0072, 0.007]
    runs = [_run(tmp_path / f"s{i}", i, m, c) for i, (m, c) in enumerate(zip(mus, coms))]
    result = spread(runs)
    assert result["seeds"] == [0, 1, 2] and result["task"] == "CubeToss" and not result["missing"]
    mu = result["values"]["mu[0]"]
    assert mu["runs"] == mus and mu["mean"] == pytest.approx(statistics.mean(mus))
    assert mu["std"] == pytest.approx(statistics.stdev(mus)) and (mu["min"], mu["max"]) == (0.17, 0.18)
    assert result["values"]["centre_of_mass[2]"]["std"] == pytest.approx(statistics.stdev(coms))
    assert result["values"]["eval.position_error_pct"]["mean"] == pytest.approx(10 * statistics.mean(mus))
    assert result["values"]["g"]["std"] == 0 and result["values"]["table_height_m"]["mean"] == -0.0019
    table = spread_table(result)
    assert "| mu[0] | 0.17 | 0.174 | 0.18 | 0.1747 |" in table


def test_one_run_has_no_std_and_a_value_not_in_every_run_is_named(tmp_path):
    assert spread([_run(tmp_path / "a", 0, 0.17, 0.006)])["values"]["mu[0]"]["std"] is None
    result = spread([tmp_path / "a", _run(tmp_path / "b", 1, 0.18, 0.007, metrics=False)])
    assert "eval.position_error_pct" not in result["values"] and "eval.position_error_pct" in result["missing"]
    assert "Not in every run: eval.position_error_pct" in spread_table(result)


def test_runs_of_another_model_and_unfinished_runs_are_refused(tmp_path):
    a = _run(tmp_path / "a", 0, 0.17, 0.006)
    b = _run(tmp_path / "b", 1, 0.18, 0.007, model="CMr-CD-CLNN")
    with pytest.raises(ConfigError, match=r"b is a run of CMr-CD-CLNN on CubeToss, not CM-CD-CLNN"):
        spread([a, b])
    (b / "learned.json").unlink()
    (b / "config.json").write_text(json.dumps({"args": {"task": "CubeToss", "model": "CM-CD-CLNN", "seed": 1}}))
    with pytest.raises(ConfigError, match="not a finished training run"):
        spread([a, b])
    with pytest.raises(ConfigError, match="at least one run"):
        spread([])


def test_the_command_prints_the_table_and_writes_the_json(tmp_path):
    runs = [str(_run(tmp_path / f"s{i}", i, mu, 0.007)) for i, mu in enumerate((0.17, 0.18))]
    res = CliRunner().invoke(app, ["spread", *runs, "--out", str(tmp_path / "spread.json")])
    assert res.exit_code == 0, res.output
    assert "CM-CD-CLNN on CubeToss, 2 runs" in res.output and "| g | 9.81 | 9.81 |" in res.output
    written = json.loads((tmp_path / "spread.json").read_text())
    assert written["values"]["mu[0]"]["runs"] == [0.17, 0.18] and "torch" in written["versions"]
    res = CliRunner().invoke(app, ["spread", str(tmp_path / "nowhere")])
    assert res.exit_code != 0 and "config.json is missing" in res.output

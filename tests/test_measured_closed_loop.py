"""The real-data pipeline closed on simulated tosses: Cube tosses recorded as the ContactNets files are (noise and
velocity columns like theirs), imported, trained briefly; the learned μ and e come back, and so does a centre of mass
off the box's centre."""

from __future__ import annotations

import json
from importlib import resources

import pytest

from diffcontact import build_task
from diffcontact.data.measured import import_tosses
from diffcontact.data.tosses import save_contactnets_npz, simulated_tosses
from diffcontact.eval.spread import spread
from diffcontact.train.run import train_run

RECOVERED = 0.02  # |learned − true| of μ and e
COM_RECOVERED = 1.5e-3  # m, each axis of the centre of mass


@pytest.mark.slow
@pytest.mark.parametrize("com", [None, [0.0, 0.0, 0.009]])
def test_cube_tosses_recorded_imported_and_learned(tmp_path, com):
    task_file: str = "Cube"
    if com is not None:  # (the Cube with its mass 9 mm toward a face, as the real cube's: docs/real_data.md)
        text = resources.files("diffcontact.tasks").joinpath("Cube.toml").read_text()
        task_file = str(tmp_path / "Cube.toml")
        (tmp_path / "Cube.toml").write_text(text.replace("[body]\n", f"[body]\ncentre_of_mass = {com}\n"))
    task = build_task(task_file)
    tosses = simulated_tosses(task, 16, seed=5, frames=60)
    save_contactnets_npz(tmp_path / "tosses.npz", tosses)
    # (short windows: many optimiser steps in a short test; the real tosses train on whole-toss windows. 20 epochs
    # (80 steps) recover μ and e to 0.002 at seed 5; 14 epochs leave e 0.09 off)
    folder = tmp_path / "data" / "Cube"
    import_tosses(tmp_path / "tosses.npz", folder, task=task_file, split=(0.75, 0.125, 0.125), window=8, stride=8)
    summary = train_run(
        task_file, data_root=tmp_path / "data", out=tmp_path / "run", epochs=20, batch_size=25, coef_lr=1.0,
        progress=False,
    )  # fmt: skip
    learned_com = summary["centre_of_mass"]["learned"]
    for got, true in zip(learned_com, com or [0.0] * 3):
        assert abs(got - true) <= COM_RECOVERED, summary["centre_of_mass"]
    learned = json.loads((tmp_path / "run" / "learned.json").read_text())
    assert learned["mu"]["identifiable"] == [True] and learned["e"]["identifiable"] == [True]
    # imported tosses are measured: the task's values are nominal, not a truth the summary could score against
    assert learned["mu"]["nominal"] == [pytest.approx(0.18)] and "true" not in learned["mu"]
    assert "max_abs_error" not in learned["e"] and learned["inertia"]["against"] == "nominal"
    # μ calibrated on the whole training tosses after the epochs (train/calibrate.py), as learned.json records
    calibration = learned["calibration"]
    assert calibration["mu"] == learned["mu"]["learned"] and len(calibration["train_objective"]) >= 3
    # the evaluation of the run's test tosses carries what it learned, the centre of mass included
    from diffcontact.eval.evaluate import evaluate_run

    metrics = evaluate_run(tmp_path / "run", pictures=False)
    assert metrics["learned"]["centre_of_mass"]["learned"] == learned_com and metrics["tosses"] == 2
    assert learned["g"] == pytest.approx(9.81) and learned["g_learned"] is False  # (the task's gravity, given)
    # what `diffcontact spread` reads of a real run: the learned values, the table and the evaluation
    values = spread([tmp_path / "run", tmp_path / "run"])["values"]
    assert values["mu[0]"]["mean"] == learned["mu"]["learned"][0] and values["mu[0]"]["std"] == 0
    assert values["eval.position_error_pct"]["runs"] == [metrics["position_error_pct"]] * 2
    assert {"g", "table_height_m", "centre_of_mass[2]", "moments[2]"} <= set(values)
    assert abs(summary["mu"]["learned"][0] - 0.18) <= RECOVERED, summary["mu"]
    assert abs(summary["e"]["learned"][0] - 0.125) <= RECOVERED, summary["e"]

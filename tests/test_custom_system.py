"""A system of one's own (examples/custom_system.py, docs/custom_systems.md): declared in a task file, simulated,
generated and learned with the same functions and commands as the packaged tasks, by the path of its file."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from diffcontact.cli import app

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "custom_system.py"


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    """The example run end to end on tiny data (48 training trajectories, 15 epochs): its folder and summary."""
    spec = importlib.util.spec_from_file_location("custom_system", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = tmp_path_factory.mktemp("box")
    return out, module.main(out, quick=True)


@pytest.mark.slow
def test_the_example_learns_e_of_its_own_system(example):
    out, summary = example
    assert summary["e"]["true"][0] == pytest.approx(0.7) and summary["mu"]["true"][0] == pytest.approx(0.2)
    assert abs(summary["e"]["learned"][0] - 0.7) < 0.05, summary["e"]
    assert len(summary["e"]["learned"]) == 21  # (3 ball pairs + 3 balls x 6 planes, one value shared)
    config = json.loads((out / "run" / "config.json").read_text())
    assert config["args"]["task"] == str((out / "box_of_balls.toml").resolve())  # (found again from anywhere)
    assert (out / "data" / "box-of-balls" / "meta.json").is_file()


@pytest.mark.slow
def test_the_commands_take_the_task_file_by_its_path(example, monkeypatch):
    out, _ = example
    monkeypatch.chdir(out)
    runner = CliRunner()
    res = runner.invoke(app, ["simulate", "./box_of_balls.toml", "--n", "2", "--steps", "6", "--out", "sim.npz",
                              "--gif", "sim.gif"])  # fmt: skip
    assert res.exit_code == 0, res.output
    with np.load(out / "sim.npz") as data:
        assert data["x"].shape == (2, 6, 3, 3)
    assert (out / "sim.gif").stat().st_size > 0
    res = runner.invoke(app, ["generate", "box_of_balls.toml", "--out", "data", "--n-train", "48", "--n-val", "8",
                              "--n-test", "8", "--no-progress"])  # fmt: skip
    assert res.exit_code == 0 and "identical, valid dataset exists in data/box-of-balls; skipped" in res.output
    res = runner.invoke(app, ["train", "./box_of_balls.toml", "--data", "data", "--out", "run1", "--epochs", "1",
                              "--batch-size", "16", "--no-progress"])  # fmt: skip
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["evaluate", "run", "--task", "./box_of_balls.toml", "--no-pictures", "--frames", "10"])
    assert res.exit_code == 0 and res.output.strip().endswith("-> run/eval"), res.output
    assert json.loads((out / "run" / "eval" / "metrics.json").read_text())["task"] == "box-of-balls"
    res = runner.invoke(app, ["evaluate", "run", "--task", "BP1", "--no-pictures"])
    assert res.exit_code == 2 and "is a run of task 'box-of-balls', not 'BP1'" in res.output
    res = runner.invoke(app, ["simulate", "./nothing.toml", "--out", "x.npz"])
    assert res.exit_code == 2 and "task file './nothing.toml' does not exist" in res.output


def test_the_documented_builder_registers_a_new_system(monkeypatch):
    """The Python block of docs/custom_systems.md runs as written: a ball dropped onto a ramp lands on it and loses
    energy (e = 0.5); its task files are validated against the tables it registered."""
    from diffcontact.config import task_from_dict
    from diffcontact.errors import ConfigError
    from diffcontact.systems import registry

    monkeypatch.setattr(registry, "SYSTEMS", dict(registry.SYSTEMS))  # (the registration ends with the test)
    text = (EXAMPLE.parents[1] / "docs" / "custom_systems.md").read_text()
    block = text.split("```python\n", 1)[1].split("```", 1)[0]
    scope: dict = {}
    exec(compile(block, "docs/custom_systems.md", "exec"), scope)
    task, x, v, hit = scope["task"], scope["x"], scope["v"], scope["hit"]
    assert hit.any(1).all() and (task.system.detector.gaps(x[:, -1]) > -1e-3).all()
    energy = task.system.energy(task.params, x[:, -1], v[:, -1])
    assert (energy < task.system.energy(task.params, x[:, 0], v[:, 0]) - 1e-3).all()
    raw = {"task": {"name": "r", "system": "ramp", "dt": 0.01, "frames": 5}, "ramp": {"mass": 1.0, "radus": 0.1}}
    with pytest.raises(ConfigError, match=r"ramp.radus is not a key of \[ramp\]; allowed keys: mass, radius, angle"):
        scope["dc"].build_task(task_from_dict(raw))
    assert "ramp" in registry.SYSTEMS

"""`diffcontact evaluate` on tiny runs: the exact model scores zero, a trained run writes every output, and a run of
another task, a missing or corrupt checkpoint, or an unknown model are one-line errors."""

from __future__ import annotations

import json
import shutil

import pytest
import torch
from torch import nn
from typer.testing import CliRunner

from diffcontact import simulator_for
from diffcontact.cli import app
from diffcontact.data.generate import generate_dataset
from diffcontact.errors import ConfigError
from diffcontact.eval import loading
from diffcontact.eval.evaluate import evaluate_run
from diffcontact.state import State
from diffcontact.systems import build_task
from diffcontact.train.run import train_run


class _Exact(nn.Module):
    """The ground-truth simulator (CM, true parameters) behind the model interface: a model without error."""

    def __init__(self, task):
        super().__init__()
        self.task, self.sim = task, simulator_for(task)

    def forward(self, x0, v0, frames):
        xs, vs, _ = self.sim.rollout(State(x0, v0), self.task.params, self.task.dt, frames)
        return xs, vs


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    generate_dataset("BP1", root / "data", n_train=8, n_val=2, n_test=3, frames=12, progress=False, echo=None)
    train_run("BP1", epochs=1, out=root / "run", data_root=root / "data", batch_size=8, progress=False)
    return root


def _exact_run(tmp_path, data_root):
    run = tmp_path / "exact"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "best-epoch=0.ckpt").write_bytes(b"")  # (the exact model has no weights)
    args = {"task": "BP1", "model": "CM-CD-CLNN", "data_root": str(data_root)}
    (run / "config.json").write_text(json.dumps({"args": args, "versions": {}}))
    return run


def test_the_exact_model_has_zero_error_and_keeps_the_true_energy(trained, tmp_path, monkeypatch):
    """The evaluation of a model without error (the ground-truth simulator in place of a run's trained model)."""
    run = _exact_run(tmp_path, trained / "data")
    monkeypatch.setattr(loading, "trained_net", lambda run, config, checkpoint: _Exact(build_task("BP1")))
    m = evaluate_run(run, pictures=False)
    assert (m["n_trajectories"], m["frames"], m["trajectory_error"]["steps"]) == (3, 12, 5)
    assert max(m["trajectory_error"]["per_trajectory"]) < 1e-12 and max(m["error_curve"]) < 1e-12
    assert m["energy"]["max_rel_deviation_max"] < 1e-12
    assert m["energy"]["shown_true"] == pytest.approx(m["energy"]["shown_predicted"], abs=1e-12)
    assert json.loads((run / "eval" / "metrics.json").read_text())["trajectory_error"] == m["trajectory_error"]


def test_a_trained_run_writes_metrics_figures_and_gif(trained):
    run = trained / "run"
    m = evaluate_run(run, frames=8)
    for name in ("metrics.json", "error.png", "energy.png", "rollout.npz", "rollout.png", "rollout.gif"):
        assert (run / "eval" / name).stat().st_size > 0, name
    err = m["trajectory_error"]
    per = torch.tensor(err["per_trajectory"])
    assert len(per) == 3 and err["mean"] == pytest.approx(float(per.mean())) and err["ci95"] > 0
    assert len(m["error_curve"]) == 8 and m["error_curve"][0] == 0.0 and m["error_curve"][4] > 0
    assert m["config"]["args"]["model"] == "CM-CD-CLNN" and "torch" in m["versions"]
    assert m["learned"]["e"]["true"][0] == pytest.approx(0.8)
    assert m["seconds"] > 0  # (the evaluation's wall time, shown in the reproduction report)


def test_errors_are_one_line_and_name_the_problem(trained, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(trained / "run", run, ignore=shutil.ignore_patterns("eval", "logs"))
    with pytest.raises(ConfigError, match="is a run of task 'BP1', not 'BP2'"):
        evaluate_run(run, task="BP2")
    config = json.loads((run / "config.json").read_text())
    config["args"]["task"] = "BP2"
    (run / "config.json").write_text(json.dumps(config))
    with pytest.raises(ConfigError, match="trained on task 'BP1', but .* records CM-CD-CLNN on 'BP2'"):
        evaluate_run(run)
    config["args"]["task"] = "BP1"
    (run / "config.json").write_text(json.dumps(config))
    best = next((run / "checkpoints").glob("best-*.ckpt"))
    (run / "learned.json").unlink()  # (then the checkpoint is found in checkpoints/)
    best.write_bytes(best.read_bytes()[:1000])
    result = CliRunner().invoke(app, ["evaluate", str(run)])
    assert result.exit_code == 2 and "not a loadable checkpoint" in result.output
    assert len(result.output.strip().splitlines()) == 1
    best.unlink()
    with pytest.raises(ConfigError, match=r"expected one checkpoints/best-\*.ckpt .* found 0"):
        evaluate_run(run)
    config["args"]["model"] = "NOPE"
    (run / "config.json").write_text(json.dumps(config))
    with pytest.raises(ConfigError, match="model 'NOPE' is not one that diffcontact trains"):
        evaluate_run(run)
    with pytest.raises(ConfigError, match="config.json is missing"):
        evaluate_run(tmp_path / "nothing")


def test_the_reproduce_worker_continues_an_interrupted_training(trained, tmp_path):
    import csv

    from diffcontact.eval.worker import main

    run = tmp_path / "run"
    shutil.copytree(trained / "run", run, ignore=shutil.ignore_patterns("eval"))
    (run / "learned.json").unlink()  # (as if killed after its first epoch's checkpoint of a 2-epoch run)
    config = json.loads((run / "config.json").read_text())
    config["args"]["epochs"] = 2  # (a cosine run is resumed to its own epochs only)
    (run / "config.json").write_text(json.dumps(config))
    args = ["BP1", "CM-CD-CLNN", "0", str(run), str(trained / "data"), "--train", "--epochs", "2"]
    assert main([*args, "--batch-size", "8", "--frames", "6"]) == 0
    assert json.loads((run / "learned.json").read_text())["epochs_trained"] == 2
    logs = sorted((run / "logs" / "csv").glob("version_*/metrics.csv"))
    epochs = [
        sorted({int(r["epoch"]) for r in csv.DictReader(p.read_text().splitlines()) if r.get("epoch")}) for p in logs
    ]
    assert epochs == [[0], [1]]  # the second session trained epoch 1 only: resumed, not restarted
    assert json.loads((run / "eval" / "metrics.json").read_text())["frames"] == 6

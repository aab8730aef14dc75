"""RunDir: the one place that names a run's files, and its checks of what it reads."""

import json
from pathlib import Path

import pytest

from diffcontact.errors import ConfigError
from diffcontact.files import write_json
from diffcontact.run_dir import RunDir


def test_a_moved_run_finds_its_best_checkpoint_in_its_own_folder(tmp_path):
    run = RunDir(tmp_path / "moved")
    run.checkpoints.mkdir(parents=True)
    (run.checkpoints / "best-epoch=3.ckpt").write_bytes(b"x")
    write_json(run.learned, {"best_checkpoint": "/elsewhere/checkpoints/best-epoch=3.ckpt"})
    assert run.best_checkpoint() == run.checkpoints / "best-epoch=3.ckpt"
    write_json(run.learned, {"best_checkpoint": "/elsewhere/checkpoints/best-epoch=4.ckpt"})
    with pytest.raises(ConfigError, match="best-epoch=4.ckpt"):
        run.best_checkpoint()


def test_without_learned_json_the_only_best_checkpoint_is_taken_and_two_are_refused(tmp_path):
    run = RunDir(tmp_path)
    with pytest.raises(ConfigError, match="found 0"):
        run.best_checkpoint()
    run.checkpoints.mkdir()
    (run.checkpoints / "best-epoch=1.ckpt").write_bytes(b"x")
    assert run.best_checkpoint().name == "best-epoch=1.ckpt"
    (run.checkpoints / "best-epoch=2.ckpt").write_bytes(b"x")
    with pytest.raises(ConfigError, match="found 2"):
        run.best_checkpoint()


def test_config_must_name_a_task_and_a_model(tmp_path):
    run = RunDir(tmp_path)
    with pytest.raises(ConfigError, match="config.json is missing"):
        run.read_config()
    run.config.write_text("{not json")
    with pytest.raises(ConfigError, match="unreadable"):
        run.read_config()
    write_json(run.config, {"args": {"task": "BP5", "model": 3}})
    with pytest.raises(ConfigError, match="must be names"):
        run.read_config()
    write_json(run.config, {"args": {"task": "BP5", "model": "CM-CD-CLNN"}})
    assert run.read_config()["args"]["model"] == "CM-CD-CLNN"


def test_metrics_and_times_of_an_unfinished_run_are_none(tmp_path):
    run = RunDir.of_cell(tmp_path, "BP5", "CM-CD-CLNN", 2)
    assert run.path == tmp_path / "runs" / "BP5" / "CM-CD-CLNN" / "seed2"
    assert run.metrics() is None and run.times() == (None, None)
    run.eval_dir().mkdir(parents=True)
    (run.eval_dir() / "metrics.json").write_text("[1, 2")  # (an evaluation cut off: not finished)
    assert run.metrics() is None
    write_json(run.eval_dir() / "metrics.json", {"seconds": 4.5})
    write_json(run.learned, {"wall_time_s": 12.0})
    assert run.metrics() == {"seconds": 4.5} and run.times() == (12.0, 4.5)
    assert json.loads(run.learned.read_text())["wall_time_s"] == 12.0


def test_the_paths_of_a_run_keep_their_names(tmp_path):
    """Runs on disk are read by these names: a change would orphan them."""
    run = RunDir(tmp_path)
    named = {
        run.config: "config.json", run.learned: "learned.json", run.coef_start: "coef_start.json",
        run.solver_failures: "solver_failures.npz", run.checkpoints: "checkpoints",
        run.last_checkpoint: "checkpoints/last.ckpt", run.logs: "logs", run.csv_logs: "logs/csv",
        run.tb_logs: "logs/tb", run.loss_figure: "loss.png", run.eval_dir(): "eval",
        run.metrics_file(): "eval/metrics.json", run.metrics_file("eval_val"): "eval_val/metrics.json",
        run.reproduce_record: "reproduce.json", run.reproduce_log: "reproduce.log",
    }  # fmt: skip
    assert {path: path.relative_to(tmp_path).as_posix() for path in named} == named
    assert RunDir.default("BP5", "CM-CD-CLNN", 3).path == Path("runs/BP5/CM-CD-CLNN/seed3")

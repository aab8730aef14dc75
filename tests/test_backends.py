"""`reproduce` on its cluster backends: Ray on a local Ray cluster and Slurm through submitit's local executor give
the same runs as the local pool; a Ray worker killed mid-cell is retried and its run resumes from its checkpoint; a
finished training is never redone."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest

from diffcontact.errors import ConfigError
from diffcontact.eval.backends import Backend
from diffcontact.eval.reproduce import reproduce
from diffcontact.run_dir import RunDir

TASK, MODEL = "BP5-e", "CM-CD-CLNN"


def _needs(engine: str) -> pytest.MarkDecorator:
    """Skip a test whose engine (an optional extra) is not installed, before its fixtures train anything."""
    return pytest.mark.skipif(importlib.util.find_spec(engine) is None, reason=f"{engine} is not installed")


def _result(out: Path) -> dict:
    """What a cell learned and scored, without its times."""
    run = RunDir.of_cell(out, TASK, MODEL, 0).path
    learned = json.loads((run / "learned.json").read_text())
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    return {
        "mu": learned["mu"]["learned"],
        "e": learned["e"]["learned"],
        "mass_ratio": learned["mass_ratio"]["learned"],
        "error": metrics["trajectory_error"]["per_trajectory"],
    }


@pytest.fixture(scope="module")
def local(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("backends") / "local"
    reproduce([TASK], [MODEL], [0], out, quick=True, epochs=2, echo=lambda _: None)
    return out, _result(out)


def test_bad_backend_settings_are_refused_by_name():
    with pytest.raises(ConfigError, match="backend = 'k8s' is not one of"):
        Backend("k8s")
    with pytest.raises(ConfigError, match="address = 'auto' is for --backend ray, not local"):
        Backend("local", address="auto")
    with pytest.raises(ConfigError, match="partition = 'gpu' is for --backend slurm, not ray"):
        Backend("ray", partition="gpu")
    with pytest.raises(ConfigError, match="time = 0 is not a whole number of minutes >= 1"):
        Backend("slurm", time_min=0)
    with pytest.raises(ConfigError, match="epochs = 0 is not a whole number >= 1"):
        reproduce([TASK], [MODEL], epochs=0)


@pytest.mark.slow
@_needs("submitit")
def test_submitit_runs_the_same_cells_as_the_local_pool(local, tmp_path):
    out = tmp_path / "slurm"
    reproduce([TASK], [MODEL], [0], out, quick=True, epochs=2, echo=lambda _: None,
              backend=Backend("slurm", cluster="local"))  # fmt: skip
    assert _result(out) == local[1]
    assert list((out / "submitit").glob("*_result.pkl"))  # (the job went through submitit)
    assert json.loads((out / "reproduce.json").read_text())["sessions"][-1]["backend"] == "slurm"


@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield ray
    ray.shutdown()


@pytest.mark.slow
@_needs("ray")
def test_ray_runs_the_same_cells_as_the_local_pool(local, ray_cluster, tmp_path):
    out = tmp_path / "ray"
    reproduce([TASK], [MODEL], [0], out, quick=True, epochs=2, echo=lambda _: None, backend=Backend("ray"))
    assert _result(out) == local[1]
    stamp = (RunDir.of_cell(out, TASK, MODEL, 0).path / "learned.json").stat().st_mtime_ns
    lines: list[str] = []
    reproduce([TASK], [MODEL], [0], out, quick=True, epochs=2, echo=lines.append, backend=Backend("ray"))
    assert (RunDir.of_cell(out, TASK, MODEL, 0).path / "learned.json").stat().st_mtime_ns == stamp
    assert not any(": done in " in line for line in lines) and lines[-1].startswith("report: ")  # (nothing run)


def _worker_of(run: Path) -> int | None:
    """The pid of the process that started the cell's worker process (the Ray worker), from /proc."""
    for proc in Path("/proc").iterdir():
        try:
            cmd = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"diffcontact.eval.worker" in cmd and str(run).encode() in cmd:
            return int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])  # (its parent's pid)
    return None


@pytest.mark.slow
@_needs("ray")
def test_a_ray_worker_killed_mid_cell_is_retried_and_resumes_from_its_checkpoint(local, ray_cluster, tmp_path):
    out = tmp_path / "killed"
    run = RunDir.of_cell(out, TASK, MODEL, 0)
    killed: list[int] = []

    def kill_after_the_first_epoch():
        deadline = time.monotonic() + 300
        while not run.last_checkpoint.is_file() and time.monotonic() < deadline:
            time.sleep(0.02)
        pid = _worker_of(run.path)
        if pid is not None:
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    killer = threading.Thread(target=kill_after_the_first_epoch)
    killer.start()
    reproduce([TASK], [MODEL], [0], out, quick=True, epochs=4, echo=lambda _: None, backend=Backend("ray"))
    killer.join()
    assert killed, "the cell ended before its worker could be killed"
    log = (run.path / "reproduce.log").read_text()
    assert log.count("$ ") == 2  # (two attempts: the killed one and Ray's retry)
    assert "training from the start" not in log  # (the retry resumed from checkpoints/last.ckpt)
    learned = json.loads(run.learned.read_text())
    assert learned["epochs_trained"] == 4 and (run.path / "eval" / "metrics.json").is_file()


@pytest.mark.slow  # (trains one epoch)
def test_the_worker_trains_afresh_only_when_the_last_checkpoint_does_not_load(tmp_path):
    from diffcontact.data.generate import generate_dataset
    from diffcontact.eval import worker

    generate_dataset("BP1", tmp_path / "data", n_train=8, n_val=4, n_test=4, frames=20, progress=False, echo=None)
    run = RunDir(tmp_path / "run")
    run.checkpoints.mkdir(parents=True)
    run.last_checkpoint.write_bytes(b"not a checkpoint")  # (as a kill half-way through its write could leave it)
    args = ["BP1", MODEL, "0", str(run.path), str(tmp_path / "data"), "--train", "--epochs", "1", "--frames", "10"]
    assert worker.main(args) == 0
    assert json.loads(run.learned.read_text())["epochs_trained"] == 1

"""The catalogue of bad inputs: each ends in one clear line (no traceback) and exit code 2 on the command
line, or a named exception from the library; nothing half-written is left behind."""

from __future__ import annotations

import errno
import json
import math
import shutil

import lightning.pytorch  # noqa: F401  (imported here: its log handler then writes to the real stdout, not a runner's)
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from diffcontact import files as files_mod
from diffcontact.cli import app
from diffcontact.data import generate_dataset, load_split
from diffcontact.errors import ConfigError, DatasetError
from diffcontact.solver import Status, solve_cone_qp
from diffcontact.systems import build_task

TINY = dict(n_train=4, n_val=2, n_test=2, frames=10, progress=False, echo=None)


def _one_line(args, match: str) -> str:
    """Run the CLI: exit code 2 and one line on the output that contains ``match``."""
    result = CliRunner().invoke(app, args)
    lines = result.output.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1 and "Traceback" not in result.output, result.output
    assert match in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    generate_dataset("BP1", root, **TINY)
    return root


@pytest.mark.parametrize(
    "args, match",
    [
        (["simulate", "NoSuchTask", "--out", "x.npz"], "ConfigError: "),
        (["simulate", "BP1", "--n", "0", "--out", "x.npz"], "ConfigError: n = 0 is not >= 1"),
        (["simulate", "BP1", "--steps", "1", "--out", "x.npz"], "ConfigError: steps = 1 is not >= 2"),
        (["simulate", "BP1", "--dynamics", "foo", "--out", "x.npz"], "ConfigError: dynamics = 'foo' is not one of"),
    ],
)
def test_simulate_mistakes(args, match, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _one_line(args, match)
    assert not list(tmp_path.iterdir())


def test_simulate_outputs_that_cannot_be_written(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("")
    base = ["simulate", "BP1", "--n", "1", "--steps", "3"]
    _one_line([*base, "--out", str(tmp_path)], "is a directory; give a file name")
    _one_line([*base, "--out", str(tmp_path / "file" / "x.npz")], "is a file, not a folder")
    _one_line([*base, "--out", str(tmp_path / "x.npz"), "--gif", str(tmp_path)], "--gif = ")
    real = files_mod.os.access
    monkeypatch.setattr(files_mod.os, "access", lambda p, mode: False if str(p) == str(tmp_path) else real(p, mode))
    _one_line([*base, "--out", str(tmp_path / "x.npz")], f"the folder {tmp_path} is not writable")  # (as root: faked)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


@pytest.mark.slow
def test_a_full_disk_is_one_line_and_leaves_no_file(tmp_path, monkeypatch):
    def full(fh, *args, **kw):
        fh.write(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez", full)
    line = _one_line(
        ["generate", "BP1", "--out", str(tmp_path), "--n-train", "2", "--n-val", "2", "--n-test", "2", "--no-progress"],
        "OSError: [Errno 28] cannot write ",
    )
    assert "train.npz: No space left on device" in line
    assert not (tmp_path / "BP1").exists()  # (no partial file, no metadata, no lock: the folder made is removed)


def test_errors_inside_generate_are_one_line(tmp_path, monkeypatch):
    import diffcontact.data.generate as gen

    def diverge(*args, **kw):
        raise FloatingPointError("BP1 frame 3: non-finite position or velocity in batch element 0")

    monkeypatch.setattr(gen, "_simulate", diverge)
    _one_line(["generate", "BP1", "--out", str(tmp_path), "--no-progress"], "FloatingPointError: BP1 frame 3")
    _one_line(["generate", "BP1", "--out", str(tmp_path / "f"), "--workers", "0"], "workers = 0 is not an integer")


@pytest.mark.parametrize("lr", ["-1", "nan", "inf", "0"])
def test_train_learning_rate_out_of_range(lr, data, tmp_path):
    _one_line(["train", "BP1", "--data", str(data), "--out", str(tmp_path / "run"), "--lr", lr], f"lr = {float(lr)}")
    assert not (tmp_path / "run").exists()


def test_train_into_a_file_and_on_a_dataset_of_another_task(data, tmp_path):
    (tmp_path / "file").write_text("")
    _one_line(["train", "BP1", "--data", str(data), "--out", str(tmp_path / "file")], "is a file; give a folder name")
    other = tmp_path / "data"
    shutil.copytree(data / "BP1", other / "BP2")  # (a BP1 dataset where BP2's should be)
    _one_line(
        ["train", "BP2", "--data", str(other), "--out", str(tmp_path / "run"), "--epochs", "1"],
        "holds a dataset of task 'BP1', not 'BP2'",
    )


def test_metadata_missing_a_key_or_pointing_outside_and_the_skip_check(data, tmp_path):
    folder = tmp_path / "BP1"
    shutil.copytree(data / "BP1", folder)
    meta = json.loads((folder / "meta.json").read_text())
    broken = json.loads(json.dumps(meta))
    del broken["splits"]["train"]["arrays"]
    (folder / "meta.json").write_text(json.dumps(broken))
    with pytest.raises(DatasetError, match=r"meta.json: splits.train lacks 'arrays'; the dataset is incomplete"):
        load_split(folder, "val")
    # (the skip check is as strong as loading: this dataset is regenerated, not skipped)
    assert not generate_dataset("BP1", tmp_path, **TINY)["skipped"]
    assert load_split(folder, "train").n == 4
    outside = json.loads(json.dumps(meta))
    outside["splits"]["test"]["file"] = "../elsewhere/test.npz"
    (folder / "meta.json").write_text(json.dumps(outside))
    with pytest.raises(DatasetError, match=r"splits.test.file = '../elsewhere/test.npz' is not a file name in the"):
        load_split(folder, "test")
    del outside["request"]["dt"]
    (folder / "meta.json").write_text(json.dumps(outside))
    _one_line(["train", "BP1", "--data", str(tmp_path), "--out", str(tmp_path / "run")], "request lacks 'dt'")


@pytest.mark.parametrize(
    "args, match",
    [
        (["bench", "solver", "--contacts", "0", "--no-reference"], "ConfigError: contacts"),
        (["bench", "solver", "--dim", "4", "--no-reference"], "ConfigError: dims"),
        (["bench", "solver", "--repeats", "0", "--no-reference"], "ConfigError: repeats"),
        (["bench", "near-psd", "--n", "0"], "ConfigError: n = 0"),
        (["bench", "simulate", "--task", "NoSuchTask"], "ConfigError: "),
        (["bench", "simulate", "--task", "BP1", "--steps", "1"], "ConfigError: steps"),
    ],
)
def test_bench_mistakes(args, match):
    _one_line(args, match)


def _problem(B=6, K=2, d=2, dtype=torch.float64):
    gen = torch.Generator().manual_seed(0)
    F = torch.randn(B, K * d, K * d, generator=gen, dtype=torch.float64)
    A = F @ F.mT + 0.1 * torch.eye(K * d, dtype=torch.float64)
    q = torch.randn(B, K * d, generator=gen, dtype=torch.float64)
    return A.to(dtype), q.to(dtype), torch.full((B, K), 0.5, dtype=dtype)


def test_solver_input_validation():
    A, q, mu = _problem()
    f, info = solve_cone_qp(A, q, mu.clone().fill_(1e60), on_failure="count", return_info=True)
    assert torch.isfinite(f).all() and (f[info.failed] == 0).all()  # (failed at a huge μ: zeros, not NaN)
    with pytest.raises(ValueError, match=r"mu must be <= 1e\+100; larger in batch elements \[0, 1, 2, 3, 4, 5\]"):
        solve_cone_qp(A, q, mu.clone().fill_(1e160), on_failure="count")
    with pytest.raises(TypeError, match="A is torch.float16: the solver takes float32 or float64"):
        solve_cone_qp(*_problem(dtype=torch.float16))
    for bad in (dict(tol=-1.0), dict(tol=math.nan), dict(tol=1e-3, acceptable_tol=1e-4)):
        with pytest.raises(ValueError, match="need 0 < tol <= acceptable_tol < 1"):
            solve_cone_qp(A, q, mu, **bad)
    for max_iter in (0, 2.5, True):
        with pytest.raises(ValueError, match=f"max_iter = {max_iter!r} is not an integer >= 1"):
            solve_cone_qp(A, q, mu, max_iter=max_iter)
    f, info = solve_cone_qp(A[:0], q[:0], mu[:0], return_info=True)  # (an empty batch)
    assert f.shape == (0, 4) and info.status.shape == (0,)
    assert Status.CONVERGED == 0


def test_rollout_arguments_and_a_nan_initial_state_of_a_constrained_system():
    from diffcontact.simulator import simulator_for
    from diffcontact.state import State

    task = build_task("CP3")
    sim = simulator_for(task)
    state = task.sample(2, 0)
    for frames in (0, 1):
        with pytest.raises(ConfigError, match=f"frames = {frames} is not an integer >= 2"):
            sim.rollout(state, task.params, task.dt, frames)
    for dt in (0.0, -0.01, math.inf):
        with pytest.raises(ConfigError, match=f"dt = {dt!r} is not a finite time step > 0"):
            sim.rollout(state, task.params, dt, 3)
    x = state.x.clone()
    x[1, 0, 0] = math.nan
    with pytest.raises(FloatingPointError, match="initial state: non-finite position or velocity in batch element 1"):
        sim.rollout(State(x, state.v), task.params, task.dt, 3)
    with pytest.raises(FloatingPointError, match=r"non-finite position or velocity in 1 batch elements \(first: 1\)"):
        sim.step(State(x, state.v), task.params, task.dt)


@pytest.mark.parametrize("name", ["BP1", "CP3", "Gyro"])
def test_an_empty_batch_rolls_out_to_empty_arrays(name):
    from diffcontact.simulator import simulator_for

    task = build_task(name)
    state = task.sample(0, 0)
    for dynamics in ("lagrangian", "hamiltonian"):
        x, v, hit = simulator_for(task, dynamics=dynamics).rollout(state, task.params, task.dt, 4)
        assert x.shape == v.shape == (0, 4, *state.x.shape[1:]) and hit.shape == (0, 4)

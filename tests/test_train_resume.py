"""Resuming a training run: the same result as an uninterrupted run, the run's own settings, one last.ckpt."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from diffcontact.data.generate import generate_dataset
from diffcontact.errors import ConfigError
from diffcontact.train.module import ContactLightningModule
from diffcontact.train.run import loss_curves, train_run

# A first float32 forward pass, in every process that trains here: the potential's orthogonal initialisation (a float32
# QR) can differ in its last bits before and after one in a process, which would make two runs differ from the start.
WARM_UP = (
    "from diffcontact.train.config import TrainConfig\nfrom diffcontact.train.module import ContactLightningModule\n"
    'ContactLightningModule(TrainConfig("BP1")).loss((torch.zeros(1, 5, 1, 2), torch.zeros(1, 5, 1, 2)))'
)


def _same_threads() -> str:
    """Code that gives a child process this process's thread count: a run continued with another one ends a few
    ulps away (the suite's earlier commands may have set this process's count)."""
    return f"from diffcontact.threads import set_threads\nset_threads({torch.get_num_threads()})\n"


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    generate_dataset("BP1", root, n_train=16, n_val=4, n_test=4, progress=False)
    exec(WARM_UP)
    return root


def _killed_at_epoch(monkeypatch, epoch: int, **kw) -> None:
    """train_run(**kw) interrupted by an exception at the start of ``epoch`` (its last.ckpt: epochs 0..epoch-1)."""

    def kill(self):
        if self.current_epoch == epoch:
            raise RuntimeError("killed")

    with monkeypatch.context() as m:
        m.setattr(ContactLightningModule, "on_train_epoch_start", kill)
        with pytest.raises(RuntimeError, match="killed"):
            train_run("BP1", progress=False, **kw)


def _state(run):
    return torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)


@pytest.fixture(scope="module")
def whole(data_root, tmp_path_factory):
    """An uninterrupted run of 4 epochs (cosine schedule, 2 batches an epoch in shuffled order): its directory."""
    run = tmp_path_factory.mktemp("whole") / "run"
    train_run("BP1", out=run, progress=False, **SETTINGS, data_root=data_root)
    return run


SETTINGS = dict(epochs=4, batch_size=8, lr=3e-3)


def _same_end(a, b) -> None:
    """Two last.ckpt of equal parameters, optimiser states and schedules, to the bit."""
    a, b = _state(a), _state(b)
    assert a["state_dict"].keys() == b["state_dict"].keys()
    for key in a["state_dict"]:
        assert torch.equal(a["state_dict"][key], b["state_dict"][key]), key
    for sa, sb in zip(a["optimizer_states"][0]["state"].values(), b["optimizer_states"][0]["state"].values()):
        assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert a["lr_schedulers"] == b["lr_schedulers"] and a["epoch"] == b["epoch"]


def test_a_resumed_run_ends_bit_identical_to_an_uninterrupted_one(data_root, whole, tmp_path, monkeypatch):
    """Interrupted after epoch 2, then ``resume`` alone (the settings come from config.json): the same parameters,
    optimiser state and learned values to the bit, and the loss curves of both sessions."""
    _killed_at_epoch(monkeypatch, 2, out=tmp_path / "cut", data_root=data_root, **SETTINGS)
    assert _state(tmp_path / "cut")["epoch"] == 1
    first_session = _state(tmp_path / "cut")["counters"]["seconds"]  # (the wall time of the first session)
    assert first_session > 0
    resumed = train_run("BP1", out=tmp_path / "cut", resume=True, progress=False)
    assert resumed["wall_time_s"] > first_session  # (the training's time over both sessions)
    _same_end(whole, tmp_path / "cut")
    learned = json.loads((whole / "learned.json").read_text())
    for key in ("mu", "e", "mass_ratio"):
        assert resumed[key]["learned"] == learned[key]["learned"]
    assert resumed["epochs_trained"] == learned["epochs_trained"] == 4
    curves = loss_curves(tmp_path / "cut" / "logs" / "csv")  # (two sessions, two logs)
    assert len(list((tmp_path / "cut" / "logs" / "csv").rglob("metrics.csv"))) == 2
    assert curves == loss_curves(whole / "logs" / "csv")
    assert list(curves["train/loss"]) == [0, 1, 2, 3]
    config = json.loads((tmp_path / "cut" / "config.json").read_text())["args"]
    assert config == json.loads((whole / "config.json").read_text())["args"]


@pytest.mark.slow
def test_a_run_killed_by_sigkill_resumes_to_the_same_end(data_root, whole, tmp_path):
    """The run in another process, SIGKILLed as soon as its first checkpoint is there (in epoch 1, or while a
    checkpoint is written: Lightning writes it to a temporary file first), then resumed here."""
    import os
    import signal
    import subprocess
    import sys
    import time

    run = tmp_path / "killed"
    code = (
        "import torch\n"
        f"from diffcontact.train.run import train_run\n{_same_threads()}{WARM_UP}\n"
        f"train_run('BP1', out={str(run)!r}, data_root={str(data_root)!r}, progress=False, **{SETTINGS!r})\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], env=os.environ.copy(), stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not (run / "checkpoints" / "last.ckpt").is_file() and proc.poll() is None:
            assert time.monotonic() < deadline, "no checkpoint written in 120 s"
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert proc.returncode == -signal.SIGKILL  # (killed, not finished)
    train_run("BP1", out=run, resume=True, progress=False)
    _same_end(whole, run)


# Run in a subprocess: the training of ``whole`` whose third write of last.ckpt (epoch 2) stops half-way with a SIGKILL.
KILLED_MID_WRITE = """
import io, os, signal, sys, torch
import diffcontact.train.run as run
from diffcontact.train.run import train_run
real, writes = run.atomic_write, []
def half_then_kill(write):
    def partial(fh):
        buffer = io.BytesIO()
        write(buffer)
        fh.write(buffer.getvalue()[: len(buffer.getvalue()) // 2])
        fh.flush()
        os.kill(os.getpid(), signal.SIGKILL)
    return partial
def atomic_write(path, write):
    writes.append(path.name)
    real(path, half_then_kill(write) if writes.count("last.ckpt") == 3 else write)
run.atomic_write = atomic_write
{threads}{warm_up}
train_run("BP1", out=sys.argv[1], data_root=sys.argv[2], progress=False, **{settings!r})
"""


@pytest.mark.slow
def test_a_checkpoint_half_written_at_a_sigkill_is_never_loaded(data_root, whole, tmp_path):
    """SIGKILL while last.ckpt of epoch 2 is written: the half-written file is a temporary one beside last.ckpt (of
    epoch 1, whole); the resumed run deletes it and ends bit-identical to the uninterrupted run."""
    import signal
    import subprocess
    import sys

    run = tmp_path / "killed"
    code = KILLED_MID_WRITE.format(threads=_same_threads(), warm_up=WARM_UP, settings=SETTINGS)
    proc = subprocess.run(
        [sys.executable, "-c", code, str(run), str(data_root)], stderr=subprocess.DEVNULL, timeout=300
    )
    assert proc.returncode == -signal.SIGKILL
    half = list((run / "checkpoints").glob(".tmp-last.ckpt.*"))
    assert len(half) == 1 and half[0].stat().st_size > 0
    assert _state(run)["epoch"] == 1
    train_run("BP1", out=run, resume=True, progress=False)
    _same_end(whole, run)
    assert not list((run / "checkpoints").glob(".tmp-*"))


def test_a_run_stopped_before_its_first_checkpoint_resumes_from_the_start(data_root, whole, tmp_path, monkeypatch):
    _killed_at_epoch(monkeypatch, 0, out=tmp_path / "early", data_root=data_root, **SETTINGS)
    assert not (tmp_path / "early" / "checkpoints" / "last.ckpt").exists()
    train_run("BP1", out=tmp_path / "early", resume=True, progress=False)
    _same_end(whole, tmp_path / "early")


@pytest.fixture(scope="module")
def finished(data_root, tmp_path_factory):
    """A finished 2-epoch run (constant lr 3e-3, batch 8): its directory."""
    run = tmp_path_factory.mktemp("finished") / "run"
    train_run("BP1", epochs=2, out=run, data_root=data_root, batch_size=8, lr=3e-3, schedule="constant", progress=False)
    return run


@pytest.mark.parametrize(
    "given, message",
    [
        (dict(model="CM-CD-CHNN"), r"model = 'CM-CD-CHNN' differs from the run's 'CM-CD-CLNN'"),
        (dict(task="BP2"), r"task = 'BP2' differs from the run's 'BP1'"),
        (dict(lr=1e-3), r"lr = 0.001 differs from the run's 0.003"),
        (dict(batch_size=4), r"batch_size = 4 differs from the run's 8"),
        (dict(seed=1), r"seed = 1 differs from the run's 0"),
        (dict(schedule="cosine"), r"schedule = 'cosine' differs from the run's 'constant'"),
        (dict(preset="published"), r"preset = 'published' differs from the run's 'default'"),
        (dict(epochs=1), r"epochs = 1 \(planned: 1\) is fewer than the 2 epochs the run has trained"),
        (dict(data_root="elsewhere"), r"data_root = 'elsewhere' differs from the run's '/"),
    ],
)
def test_resume_refuses_other_settings_before_writing_anything(finished, given, message):
    before = {p: p.read_bytes() for p in (finished / "config.json", finished / "checkpoints" / "last.ckpt")}
    with pytest.raises(ConfigError, match=message):
        train_run(given.pop("task", "BP1"), out=finished, resume=True, progress=False, **given)
    assert before == {p: p.read_bytes() for p in before}


def test_a_cosine_schedule_is_not_extended(whole):
    before = (whole / "config.json").read_bytes()
    with pytest.raises(ConfigError, match=r"epochs = 5 differs from the run's 4, over which its cosine learning rate"):
        train_run("BP1", out=whole, resume=True, epochs=5, progress=False)
    assert (whole / "config.json").read_bytes() == before


def test_resume_keeps_the_runs_settings_and_a_moved_run_its_checkpoints(finished, tmp_path):
    """A copied (moved) finished run resumed to 3 epochs with only the equal values given: the recorded lr (not the
    preset's), one last.ckpt and one best checkpoint, both in the new folder."""
    run = tmp_path / "moved"
    shutil.copytree(finished, run)
    given = dict(
        epochs=3,
        lr=3e-3,
        batch_size=8,
        data_root=json.loads((run / "config.json").read_text())["args"]["data_root"] + "/.",
    )
    summary = train_run("BP1", out=run, resume=True, progress=False, **given)
    assert summary["epochs_trained"] == 3
    state = _state(run)
    assert [g["lr"] for g in state["optimizer_states"][0]["param_groups"]] == pytest.approx([3e-3, 5e-4, 5e-4])
    assert json.loads((run / "config.json").read_text())["args"]["epochs"] == 3
    names = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert names[-1] == "last.ckpt" and len(names) == 2 and names[0].startswith("best-"), names
    best = summary["best_checkpoint"]
    assert best == str(run / "checkpoints" / names[0]) and state["epoch"] == 2
    callback = next(v for k, v in state["callbacks"].items() if k.startswith("ModelCheckpoint{"))  # (as before)
    assert callback["best_model_score"] is not None and str(run) in callback["best_model_path"]
    again = train_run("BP1", out=run, resume=True, progress=False)  # (nothing left to train: the best is found)
    assert again["best_checkpoint"] == best and again["mu"] == summary["mu"]


def test_a_fresh_run_beside_checkpoints_and_a_damaged_checkpoint_are_clear_errors(finished, tmp_path):
    with pytest.raises(ConfigError, match="already holds the checkpoints of a run: continue it with --resume"):
        train_run("BP1", epochs=1, out=finished, data_root=finished.parent, progress=False)
    run = tmp_path / "damaged"
    shutil.copytree(finished, run)
    config = json.loads((run / "config.json").read_text())
    del config["args"]["mu_coef_lr"]
    (run / "config.json").write_text(json.dumps(config))
    with pytest.raises(ConfigError, match=r"config.json lacks \['mu_coef_lr'\] \(a run of an older version\)"):
        train_run("BP1", out=run, resume=True, progress=False)
    last = run / "checkpoints" / "last.ckpt"
    (run / "config.json").write_bytes((finished / "config.json").read_bytes())
    last.write_bytes(last.read_bytes()[:1000])  # (as a kill while it is written would leave it)
    with pytest.raises(ConfigError, match="is not a readable training run"):
        train_run("BP1", out=run, resume=True, progress=False)


def test_the_cli_names_the_setting_in_one_line(finished):
    from typer.testing import CliRunner

    from diffcontact.cli import app

    result = CliRunner().invoke(app, ["train", "BP1", "--out", str(finished), "--resume", "--model", "CM-CD-CHNN"])
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [
        "ConfigError: --resume: model = 'CM-CD-CHNN' differs from the run's 'CM-CD-CLNN' "
        f"({finished / 'config.json'}); leave it out to continue the run as it was, or train into another --out"
    ]


def test_a_checkpoint_of_another_model_is_refused(finished, data_root, tmp_path):
    other = train_run("BP1", "CM-CD-CHNN", epochs=1, out=tmp_path / "chnn", data_root=data_root, progress=False)
    run = tmp_path / "mixed"
    shutil.copytree(finished, run)
    shutil.copy(tmp_path / "chnn" / "checkpoints" / "last.ckpt", run / "checkpoints" / "last.ckpt")
    assert other["epochs_trained"] == 1
    with pytest.raises(ConfigError, match=r"last.ckpt is of model 'CM-CD-CHNN', config.json records 'CM-CD-CLNN'"):
        train_run("BP1", out=run, resume=True, progress=False)


def test_last_ckpt_is_the_last_epoch_when_the_validation_loss_stops_improving(data_root, tmp_path, monkeypatch):
    # (Lightning writes last.ckpt only in a step that writes a best checkpoint: here only epoch 0 is the best)
    loss = ContactLightningModule.loss

    def worse_every_epoch(self, batch, *args, **kwargs):
        return loss(self, batch, *args, **kwargs) + (0.0 if self.training else 10.0 * self.current_epoch)

    monkeypatch.setattr(ContactLightningModule, "loss", worse_every_epoch)
    run = tmp_path / "run"
    train_run("BP1", out=run, progress=False, epochs=3, batch_size=8, data_root=data_root)
    assert [p.name for p in sorted((run / "checkpoints").glob("best-*.ckpt"))] == ["best-epoch=0.ckpt"]
    assert _state(run)["epoch"] == 2  # (the last epoch trained: a kill after it would lose nothing)

"""Training on two processes (Lightning DDP, gloo on the CPU): it completes, learns what one process learns, sums the
counters of both processes and writes its files once."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from diffcontact.data.generate import generate_dataset
from diffcontact.train.config import TrainConfig
from diffcontact.train.module import ContactLightningModule
from diffcontact.train.run import train_run

SETTINGS = dict(epochs=8, lr=2e-2, coef_lr=1.0)  # (μ and e move by more than 0.1 from their start)

# Run as a script (Lightning's DDP launcher starts the second process by running it again): every training step
# counts one forward failure, to see that the counters are summed over the processes.
SCRIPT = """
import sys
from diffcontact.train.module import ContactLightningModule
from diffcontact.train.run import train_run

step = ContactLightningModule.training_step
def counted(self, batch, batch_idx):
    self.forward_failures += 1
    return step(self, batch, batch_idx)
ContactLightningModule.training_step = counted
train_run("BP1", out=sys.argv[1], data_root=sys.argv[2], batch_size=4, devices=2, accelerator="cpu", progress=False,
          **{settings!r})
"""


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    generate_dataset("BP1", root, n_train=16, n_val=4, n_test=4, progress=False, echo=None)
    return root


@pytest.mark.slow
def test_two_processes_learn_what_one_learns_and_sum_their_counters(data_root, tmp_path):
    one = train_run("BP1", out=tmp_path / "one", data_root=data_root, batch_size=8, progress=False, **SETTINGS)
    script = tmp_path / "ddp_run.py"
    script.write_text(SCRIPT.format(settings=SETTINGS))
    run = tmp_path / "two"
    proc = subprocess.run(
        [sys.executable, str(script), str(run), str(data_root)], capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "training on 2 process(es) (2 device(s) x 1 node(s), cpu): batch 4 per process, effective batch 8, " in (
        proc.stdout + proc.stderr
    )
    two = json.loads((run / "learned.json").read_text())
    assert two["processes"] == 2 and two["epochs_trained"] == one["epochs_trained"] == 8
    # both processes' steps counted: 8 chunks each, 2 batches of 4 an epoch, 8 epochs
    assert two["forward_failures"] == 2 * 2 * 8 and two["skipped_steps"] == 0
    start = ContactLightningModule(TrainConfig("BP1")).learned  # (seed 0, as both runs)
    for key in ("mu", "e"):  # (another batch order: the same change from the start within a quarter of it)
        a, b, s = one[key]["learned"][0], two[key]["learned"][0], float(getattr(start, key).detach()[0])
        assert abs(a - s) > 0.1 and abs(b - a) < 0.25 * abs(a - s), (key, s, a, b)
    parallel = json.loads((run / "config.json").read_text())["parallel"]
    assert parallel == dict(
        processes=2,
        accelerator="cpu",
        strategy="ddp",
        batch_per_process=4,
        effective_batch=8,
        lr=2e-2,
        lr_scaling="none (the learning rate is not scaled with the effective batch)",
    )
    # the files of one writer: one log of each kind, one last and one best checkpoint (and the refined one), no lock
    assert sorted(p.name for p in run.iterdir()) == ["checkpoints", "config.json", "learned.json", "logs", "loss.png"]
    assert [p.name for p in (run / "logs" / "csv").iterdir()] == ["version_0"]
    refined = json.loads((run / "learned.json").read_text())["refinement"]  # (written once: by rank 0)
    extra = ["refined-best-epoch=7.ckpt"] if refined["kept"] and refined["iterations"] else []
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["best-epoch=7.ckpt", "last.ckpt", *extra]

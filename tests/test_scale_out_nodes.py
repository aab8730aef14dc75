"""Training on several machines, emulated on one: two ``torchrun`` launchers with node ranks 0 and 1 meeting at
127.0.0.1 (docs/scaling.md) train as a two-process run on one machine does, to the bit."""

from __future__ import annotations

import json
import socket
import subprocess
import sys

import pytest
import torch

from diffcontact.data.generate import generate_dataset

SETTINGS = ["--epochs", "2", "--batch-size", "4", "--lr", "2e-2", "--coef-lr", "1", "--no-progress"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _parameters(run) -> dict:
    return torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]


@pytest.mark.slow
def test_two_nodes_of_one_process_train_as_two_processes_on_one_machine(tmp_path):
    data = tmp_path / "data"
    generate_dataset("BP1", data, n_train=16, n_val=4, n_test=4, progress=False, echo=None)
    train = [sys.executable, "-m", "diffcontact.cli", "train", "BP1", "--data", str(data), *SETTINGS]
    one_machine = tmp_path / "two-procs"
    proc = subprocess.run([*train, "--out", str(one_machine), "--devices", "2"], capture_output=True, text=True,
                          timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    nodes = tmp_path / "two-nodes"
    port = str(_free_port())
    launchers = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "torch.distributed.run",
                "--nnodes",
                "2",
                "--nproc-per-node",
                "1",
                "--node-rank",
                str(rank),
                "--master-addr",
                "127.0.0.1",
                "--master-port",
                port,
                "-m",
                "diffcontact.cli",
                *train[3:],
                "--out",
                str(nodes),
                "--devices",
                "1",
                "--num-nodes",
                "2",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )  # fmt: skip
        for rank in (0, 1)
    ]
    logs = [p.communicate(timeout=600)[0] for p in launchers]
    assert [p.returncode for p in launchers] == [0, 0], logs[0][-3000:] + logs[1][-3000:]
    assert "training on 2 process(es) (1 device(s) x 2 node(s), cpu): batch 4 per process, effective batch 8" in logs[0]
    learned = json.loads((nodes / "learned.json").read_text())
    assert learned["processes"] == 2 and learned["epochs_trained"] == 2
    a, b = _parameters(nodes), _parameters(one_machine)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)

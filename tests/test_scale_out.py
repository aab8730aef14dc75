"""Many processes on one output: lock files (generate, train), parallel generation byte-identical to serial."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from typer.testing import CliRunner

from diffcontact.cli import app
from diffcontact.data import generate_dataset, load_split
from diffcontact.data.store import SPLITS
from diffcontact.lock import LOCK_NAME, LockError, output_lock

TINY = dict(n_train=5, n_val=3, n_test=3, frames=12, progress=False, echo=None)

# Run in a subprocess: hold the lock of sys.argv[1], say so on stdout, then sleep until killed.
HOLDER = """
import sys, time
from diffcontact.lock import output_lock
with output_lock(sys.argv[1]):
    print("locked", flush=True)
    time.sleep(600)
"""


@pytest.fixture
def holder(tmp_path):
    """A process holding the lock of tmp_path/out: (its folder, the process)."""
    folder = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        yield folder, proc
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        proc.stdout.close()


@pytest.mark.slow
def test_a_locked_output_is_a_clear_error_naming_the_holder_and_a_dead_holders_lock_is_taken_over(holder):
    folder, proc = holder
    lock = folder / LOCK_NAME
    record = json.loads(lock.read_text())
    assert record["pid"] == proc.pid
    with pytest.raises(LockError, match=rf"{folder} is being written by pid {proc.pid} on .*: lock {lock}; wait"):
        with output_lock(folder):
            pass
    start = time.monotonic()
    with pytest.raises(LockError):
        with output_lock(folder, wait=0.5, poll=0.1):
            pass
    assert time.monotonic() - start >= 0.5
    proc.send_signal(signal.SIGKILL)  # (its record stays behind, its flock goes with it)
    proc.wait()
    assert json.loads(lock.read_text())["pid"] == proc.pid
    with output_lock(folder) as path:
        assert json.loads(path.read_text())["pid"] == os.getpid()
    assert not lock.exists() and folder.is_dir()


def test_generate_and_train_into_a_locked_output_fail_in_one_line_and_write_nothing(holder):
    folder, proc = holder
    runner = CliRunner()
    lines = lambda r: r.output.strip().splitlines()  # noqa: E731
    task_folder = folder.parent / "BP1"
    with output_lock(task_folder):
        result = runner.invoke(app, ["generate", "BP1", "--out", str(folder.parent), "--n-train", "4"])
    assert result.exit_code == 2 and len(lines(result)) == 1
    assert lines(result)[0].startswith(f"LockError: {task_folder} is being written by pid {os.getpid()} on ")
    result = runner.invoke(app, ["train", "BP1", "--out", str(folder), "--data", str(folder.parent), "--epochs", "1"])
    assert result.exit_code == 2 and len(lines(result)) == 1
    assert f"LockError: {folder} is being written by pid {proc.pid} on " in lines(result)[0]
    assert f"lock {folder / LOCK_NAME}" in lines(result)[0]
    assert sorted(p.name for p in folder.iterdir()) == [LOCK_NAME]  # (no config.json, no checkpoints)


@pytest.mark.slow
def test_two_generate_commands_at_once_leave_one_valid_dataset(tmp_path):
    """Two processes generating the same task into one root with other sizes: whatever the interleaving, one
    writes the dataset and the other stops with a one-line LockError or ConfigError; the dataset loads."""
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "diffcontact.cli",
                "generate",
                "BP1",
                "--out",
                str(tmp_path),
                "--n-train",
                str(n),
                "--n-val",
                "2",
                "--n-test",
                "2",
                "--no-progress",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for n in (6, 7)
    ]
    results = [(p.wait(timeout=300), *p.communicate()) for p in procs]
    codes = sorted(r[0] for r in results)
    assert codes == [0, 2], results
    failed = next(r for r in results if r[0] == 2)
    assert len(failed[2].strip().splitlines()) == 1 and failed[2].startswith(("LockError:", "ConfigError:")), failed
    n = load_split(tmp_path / "BP1", "train").n
    assert n in (6, 7) and not list((tmp_path / "BP1").glob(".tmp-*"))
    assert not (tmp_path / "BP1" / LOCK_NAME).exists()


@pytest.mark.slow
def test_parallel_generation_is_byte_identical_to_serial(tmp_path, monkeypatch):
    """Blocks of 2 trajectories (the splits of 5 and 3: 3 and 2 blocks), one after the other or in 2 processes."""
    import diffcontact.data.generate as gen

    monkeypatch.setattr(gen, "BLOCK", 2)
    assert gen.blocks(5) == [0, 2, 3, 5] and gen.blocks(3) == [0, 2, 3]
    serial = generate_dataset("BP1", tmp_path / "serial", **TINY)
    parallel = generate_dataset("BP1", tmp_path / "parallel", **TINY, workers=2)
    for split in SPLITS:
        a = (tmp_path / "serial" / "BP1" / f"{split}.npz").read_bytes()
        b = (tmp_path / "parallel" / "BP1" / f"{split}.npz").read_bytes()
        assert a == b, split
        assert serial["splits"][split]["sha256"] == parallel["splits"][split]["sha256"]
    assert serial["request"] == parallel["request"] and serial["simulation_block"] == 2

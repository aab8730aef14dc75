"""One thread setting (diffcontact.threads): CPUs available (affinity, cgroup quota), --threads plumbed to torch,
numba and the solver's pool, quiet OpenMP waiting set before torch loads, and `bench train` on a small task."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numba
import pytest
import torch
from typer.testing import CliRunner

from diffcontact.cli import app
from diffcontact.errors import ConfigError
from diffcontact.solver import kernel
from diffcontact.threads import (
    JOB_MEMORY,
    available_cpus,
    available_memory,
    cgroup_cpu_limit,
    default_jobs,
    quiet_waiting_env,
    set_threads,
    spin_warning,
    thread_env,
)


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads(), numba.get_num_threads()
    yield
    torch.set_num_threads(before[0])
    numba.set_num_threads(before[1])


def test_cgroup_v2_quota(tmp_path):
    f = tmp_path / "cpu.max"
    f.write_text("150000 100000\n")
    assert cgroup_cpu_limit(f, tmp_path / "none") == pytest.approx(1.5)
    f.write_text("max 100000\n")
    assert cgroup_cpu_limit(f, tmp_path / "none") is None
    f.write_text("garbage\n")
    assert cgroup_cpu_limit(f, tmp_path / "none") is None


def test_cgroup_v1_quota_and_no_files(tmp_path):
    v1 = tmp_path / "cpu"
    v1.mkdir()
    assert cgroup_cpu_limit(tmp_path / "cpu.max", v1) is None  # (neither file)
    (v1 / "cpu.cfs_period_us").write_text("100000\n")
    (v1 / "cpu.cfs_quota_us").write_text("-1\n")
    assert cgroup_cpu_limit(tmp_path / "cpu.max", v1) is None
    (v1 / "cpu.cfs_quota_us").write_text("50000\n")
    assert cgroup_cpu_limit(tmp_path / "cpu.max", v1) == pytest.approx(0.5)


def test_available_cpus_takes_the_smaller_of_affinity_and_quota():
    assert available_cpus({0, 1, 2, 3}, None, read_cgroup=False) == 4
    assert available_cpus({0, 1, 2, 3}, 1.5) == 2  # (a fractional quota rounds up)
    assert available_cpus({0, 1, 2, 3}, 0.3) == 1
    assert available_cpus({5}, 8.0) == 1
    assert available_cpus() == min(len(os.sched_getaffinity(0)), available_cpus(read_cgroup=False)) >= 1


def test_default_jobs_one_per_cpu_as_memory_allows(tmp_path):
    assert default_jobs(4, 100 * JOB_MEMORY) == 4
    assert default_jobs(64, 10.5 * JOB_MEMORY) == 10  # (memory, not CPUs, limits a big machine)
    assert default_jobs(4, 0.2 * JOB_MEMORY) == 1
    info = tmp_path / "meminfo"
    info.write_text("MemTotal:       24000000 kB\nMemAvailable:   3000000 kB\n")
    assert available_memory(info) == 3000000 * 1024
    assert available_memory(tmp_path / "missing") is None
    assert 1 <= default_jobs() <= available_cpus()


def test_quiet_waiting_keeps_the_users_setting():
    env = {"OMP_WAIT_POLICY": "ACTIVE"}
    assert quiet_waiting_env(env) == {"KMP_BLOCKTIME": "0"}
    assert env == {"OMP_WAIT_POLICY": "ACTIVE", "KMP_BLOCKTIME": "0"}
    child = thread_env(3, {"PATH": "/bin"})
    assert child["OMP_NUM_THREADS"] == "3" and child["NUMBA_NUM_THREADS"] == "3"
    assert child["OMP_WAIT_POLICY"] == "PASSIVE" and child["PATH"] == "/bin"


@pytest.mark.slow
def test_passive_waiting_is_set_before_torch_is_imported():
    """The OpenMP runtime reads OMP_WAIT_POLICY when torch loads it: `import diffcontact` must set it first."""
    probe = (
        "import os, sys\n"
        "seen = []\n"
        "class Probe:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'torch' and not seen:\n"
        "            seen.append(os.environ.get('OMP_WAIT_POLICY'))\n"
        "sys.meta_path.insert(0, Probe())\n"
        "import diffcontact\n"
        "print(seen[0])\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "KMP_BLOCKTIME")}
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "PASSIVE"
    env["OMP_WAIT_POLICY"] = "ACTIVE"  # (the user's choice wins)
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "ACTIVE"


def test_spin_warning_names_the_cause_and_the_fix():
    class FakeTorch:
        def __init__(self, threads):
            self.get_num_threads = lambda: threads

    msg = spin_warning({}, {"torch": FakeTorch(2)})
    assert "imported before diffcontact" in msg and "OMP_WAIT_POLICY=PASSIVE" in msg
    assert spin_warning({}, {}) is None  # torch not loaded yet: the policy is set in time
    assert spin_warning({"OMP_WAIT_POLICY": "ACTIVE"}, {"torch": FakeTorch(2)}) is None  # the user's choice
    assert spin_warning({}, {"torch": FakeTorch(1)}) is None  # one thread: no worker to spin


@pytest.mark.slow
def test_importing_torch_first_warns_once_and_diffcontact_first_does_not():
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "KMP_BLOCKTIME", "OMP_NUM_THREADS")}
    env["OMP_NUM_THREADS"] = "2"
    runs = {
        order: subprocess.run([sys.executable, "-c", order], env=env, capture_output=True, text=True, check=True)
        for order in ("import torch; import diffcontact", "import diffcontact; import torch")
    }
    warned = runs["import torch; import diffcontact"].stderr
    assert warned.count("RuntimeWarning: torch was imported before diffcontact") == 1, warned
    assert "RuntimeWarning" not in runs["import diffcontact; import torch"].stderr


def test_set_threads_reaches_torch_numba_and_the_solver_pool(restore_threads):
    calls = []
    count = 64 * kernel.current_width()
    for n in (1, 2):
        assert set_threads(n) == n
        assert torch.get_num_threads() == n and numba.get_num_threads() == min(n, numba.config.NUMBA_NUM_THREADS)
        calls.clear()
        kernel.parallel(lambda a, b: calls.append((a, b)), count)
        assert len(calls) == numba.get_num_threads()
        assert sorted(calls)[0][0] == 0 and sorted(calls)[-1][1] == count
    with pytest.raises(ConfigError, match="threads = 0 is not an integer >= 1"):
        set_threads(0)


def test_bench_train_on_a_small_task(tmp_path, restore_threads):
    out = tmp_path / "bench.json"
    args = ["bench", "train", "BP5-e", "--batch", "4", "--warmup", "0", "--repeats", "1", "--busy", "1"]
    res = CliRunner().invoke(app, [*args, "--threads", "1", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert torch.get_num_threads() == 1 and numba.get_num_threads() == 1
    result = json.loads(out.read_text())
    assert result["header"]["torch_threads"] == 1 and result["header"]["busy"] == 1
    (row,) = result["rows"]
    assert row["task"] == "BP5-e" and row["model"] == "CM-CD-CLNN" and row["batch"] == 4
    assert row["step"] == pytest.approx(row["forward"] + row["backward"] + row["optimiser"])
    assert 0 <= row["contact_share_cpu"] <= 1
    for key in ("cpu", "dynamics", "contact", "optimiser", "step_no_contacts", "step_busy", "busy_ratio"):
        assert row[key] >= 0
    assert "| BP5-e | CM-CD-CLNN |" in res.output
    res = CliRunner().invoke(app, ["bench", "train", "BP5-e", "--models", "XX"])
    assert res.exit_code == 2 and "model = 'XX' is not one of" in res.output


def test_bench_train_times_the_model_and_batch_that_train_makes_by_default():
    """The task file's settings (the Rope's linked potential) and the default preset's batch of 50 chunks."""
    from diffcontact.bench.train import StepTimer, synthetic_batch
    from diffcontact.models.params import LinkedPotential

    data, _ = synthetic_batch("Rope", "CM-CD-CLNN", 2)
    timer = StepTimer("Rope", "CM-CD-CLNN", data)
    assert isinstance(timer.module.net.params.potential, LinkedPotential) and timer.module.config.batch_size == 50


def test_bench_train_flags_a_step_without_contacts_slower_than_with_them():
    """The contact model's share is the difference of two timed steps; where the step without contacts is the
    slower one (a disturbed measurement), the row says so instead of reporting a share of 0."""
    from diffcontact.bench.train import time_model

    class Timer:
        baseline = False

        def step(self, contacts=True):
            t = 0.09 if contacts else 0.10
            return {"forward": t / 2, "backward": t / 2, "optimiser": 0.002, "contact_fwd": 0.02, "cpu": t}

    row = time_model(Timer(), warmup=0, repeats=3, busy=[])
    assert row["disturbed"] and row["contact"] == 0.0


@pytest.mark.slow
def test_busy_processes_die_with_the_benchmark_even_if_it_is_killed():
    code = (
        "import signal, time\n"
        "from diffcontact.bench.train import start_busy\n"
        "(p,) = start_busy(1)\n"
        "p.send_signal(signal.SIGSTOP)\n"  # (as between measurements)
        "print(p.pid, flush=True)\n"
        "time.sleep(60)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    child = int(parent.stdout.readline())
    parent.kill()
    parent.wait()
    parent.stdout.close()
    for _ in range(50):  # (gone, or a zombie waiting to be reaped by init)
        try:
            state = Path(f"/proc/{child}/stat").read_text().split()[2]
        except FileNotFoundError:
            break
        if state in ("Z", "X"):
            break
        time.sleep(0.1)
    else:
        pytest.fail(f"busy process {child} still alive (state {state}) after the benchmark was killed")


COMMANDS = ["train", "generate", "simulate", "evaluate", "reproduce", "bench solver", "bench simulate", "bench train"]


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_takes_threads(command):
    res = CliRunner().invoke(app, [*command.split(), "--help"], env={"COLUMNS": "200"})
    assert res.exit_code == 0 and "--threads" in res.output


def test_one_thread_runs_its_block_on_one_thread_and_restores_the_setting():
    import torch

    from diffcontact.threads import one_thread

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        with one_thread():
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
        with pytest.raises(RuntimeError, match="inside"), one_thread():
            raise RuntimeError("inside")
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)

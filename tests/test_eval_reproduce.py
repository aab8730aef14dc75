"""`diffcontact reproduce --quick` end to end, killed after its first run and resumed: the report has every section,
and the finished run is not redone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from diffcontact.errors import ConfigError
from diffcontact.eval.reproduce import Progress, reproduce
from diffcontact.run_dir import RunDir

TASKS, MODELS = ["BP5-e", "BP5"], ["CM-CD-CLNN", "MLP-CD-CLNN"]


@pytest.fixture(scope="module")
def resumed(tmp_path_factory):
    out = tmp_path_factory.mktemp("reproduce") / "out"
    args = ["reproduce", "--quick", "--out", str(out), "--jobs", "1"]
    args += ["--tasks", TASKS[0], "-t", TASKS[1], "--models", ",".join(MODELS)]  # (repeated, or comma-separated)
    env = dict(os.environ, OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE")
    proc = subprocess.Popen(
        [sys.executable, "-m", "diffcontact.cli", *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=env,
        start_new_session=True,  # (its own process group: the kill reaches its workers too)
    )
    first = RunDir.of_cell(out, "BP5-e", "CM-CD-CLNN", 0).path
    deadline = time.monotonic() + 600
    while not (first / "eval" / "metrics.json").is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert (first / "eval" / "metrics.json").is_file(), "the first run did not finish"
    second = RunDir.of_cell(out, "BP5", "CM-CD-CLNN", 0).path
    killed = {"report": (out / "report.md").is_file(), "second": (second / "eval" / "metrics.json").is_file()}
    stamps = {p: p.stat().st_mtime_ns for p in (first / "eval" / "metrics.json", first / "learned.json")}
    lines: list[str] = []
    report = reproduce(TASKS, MODELS, [0], out, quick=True, jobs=1, echo=lines.append, command="test")
    return out, report, killed, stamps, lines


@pytest.mark.slow
def test_a_killed_reproduction_resumes_without_redoing_finished_runs(resumed):
    out, report, killed, stamps, lines = resumed
    assert not killed["report"] and not killed["second"]  # (killed after the first run, before the second ended)
    assert all(p.stat().st_mtime_ns == t for p, t in stamps.items())  # the first run: neither trained nor evaluated
    assert lines[-1] == f"report: {report}"
    assert any(line.startswith("[1/4 done] running: BP5-e/MLP-CD-CLNN/seed0") for line in lines)
    assert not any(line.startswith("BP5-e/CM-CD-CLNN/seed0: done") for line in lines)
    assert any(line.startswith("BP5/CM-CD-CLNN/seed0: done in") for line in lines)
    assert (RunDir.of_cell(out, "BP5", "CM-CD-CLNN", 0).path / "eval" / "rollout.gif").is_file()


@pytest.mark.slow  # (its fixture trains and evaluates a quick reproduction: about 30 s)
def test_the_quick_report_has_every_section_and_a_row_for_every_run(resumed):
    out, report, *_ = resumed
    text = report.read_text()
    for heading in (
        "## Runs",
        "## Table 2",
        "## Per-slot μ and e",
        "### BP5: learned μ per contact slot",
        "## Learned mass ratios",
        "## Fig. 3",
        "## Fig. 4",
        "## Fig. 5",
        "## Rollouts",
    ):
        assert heading in text, heading
    assert "| BP5-e (0, 1) |" in text and "/ 0, 1 |" in text  # Table 2 beside the published values
    assert "(published 2.34e-05 ± 1.3e-05)" in text
    for task in TASKS:
        assert f"| {task} | MLP-CD-CLNN | 0 | done |" in text  # (a baseline: trained and evaluated alike)
        assert f"| {task} | CM-CD-CLNN | 0 | done |" in text
        assert (out / "figures" / f"rollout_{task}.png").stat().st_size > 0
    for name in ("fig3_errors.png", "fig4_curves.png", "fig5_energy.png"):
        assert (out / "figures" / name).stat().st_size > 0
        assert f"](figures/{name})" in text
    assert "| training (s) | evaluation (s) |" in text and "| — | — |" not in text.split("## Table 2")[0]
    with pytest.raises(ConfigError, match="holds a quick reproduction: give another --out for a full one"):
        reproduce(TASKS, MODELS, [0], out, quick=False)


def test_energy_deviations_are_shown_readably():
    from diffcontact.eval.report import _pct

    assert (_pct(0.01234), _pct(2.5), _pct(float("inf"))) == ("1.23%", "250.00%", "diverged")
    assert _pct(4.5e83) == "4.5e+85 %"  # (a model that left the table: no 86-digit percentage)


def test_bad_arguments_and_the_time_left():
    with pytest.raises(ConfigError, match="model 'XX' is not one of"):
        reproduce(["BP5"], ["XX"])
    with pytest.raises(ConfigError, match="task 'NOPE' is not one of"):
        reproduce(["NOPE"])
    progress = Progress(total=4, done=0, jobs=2, echo=lambda _: None)
    assert progress.left() is None
    progress.durations, progress.done = [10.0, 20.0], 2
    assert progress.left() == pytest.approx(2 * 15.0 / 2)  # (2 runs to go, 15 s each, 2 at a time)
    # with expected times (earlier runs of the same model): a slow baseline counts as slow from the start
    progress = Progress(3, 0, 1, lambda _: None, expected={"a": 100.0, "b": 10.0}, pending=["a", "b", "c"])
    assert progress.left() is None  # ("c" has no estimate until a run finishes)
    progress.expected["c"] = 1.0
    assert progress.left() == pytest.approx(111.0)
    progress.start("a")
    progress.running["a"] -= 40.0  # (a has run for 40 s)
    assert progress.left() == pytest.approx(60.0 + 11.0, abs=0.1)


def test_a_running_run_is_shown_at_its_epoch_and_its_time_left_follows_its_pace(tmp_path):
    """A run resumed at epoch 2 of 10 that has reached epoch 4 in 40 s has 6 epochs left at 20 s each; the line
    shows its epoch; a run whose epochs have not advanced here falls back on its expected time."""
    run = tmp_path / "run"
    (run / "logs" / "csv" / "version_0").mkdir(parents=True)
    (run / "config.json").write_text('{"args": {"task": "BP5", "model": "CM-CD-CLNN", "epochs": 10}}')
    log = run / "logs" / "csv" / "version_0" / "metrics.csv"

    def logged(last_epoch: int) -> None:  # (3 rows an epoch; the epoch is not the first column)
        rows = [f"{0.1 * e},{e},{3 * e + k}" for e in range(last_epoch + 1) for k in range(3)]
        log.write_text("\n".join(["train/loss,epoch,step", *rows]) + "\n")

    logged(2)
    lines = []
    progress = Progress(1, 0, 1, lines.append, expected={"a": 1000.0}, pending=["a"], runs={"a": run})
    progress.start("a")
    progress.running["a"] -= 40.0
    assert progress.left() == pytest.approx(1000.0 - 40.0, abs=0.1)  # (no epoch done here yet: the expected time)
    logged(4)
    assert progress.left() == pytest.approx(6 * 20.0, abs=0.1)
    progress.show()
    assert "a (epoch 4/10, 0m40s)" in lines[-1] and "left: about 2m00s" in lines[-1]
    log.write_text("train/loss,epoch\n0.1,not-a-number\n")  # (an unreadable log: the expected time again)
    assert progress.left() == pytest.approx(960.0, abs=0.1)


def test_expected_times_come_from_the_same_models_earlier_runs(tmp_path):
    import json

    from diffcontact.eval.reproduce import Cell, expected_seconds

    for task, model, seconds in (("A", "slow", 1000.0), ("A", "fast", 100.0), ("B", "fast", 300.0)):
        run = tmp_path / "runs" / task / model / "seed0"
        (run / "eval").mkdir(parents=True)
        (run / "learned.json").write_text(json.dumps({"wall_time_s": seconds}))
        (run / "eval" / "metrics.json").write_text(json.dumps({"seconds": 10.0}))
    cells = [
        Cell("B", "slow", 0, tmp_path / "x", "train"),
        Cell("A", "fast", 1, tmp_path / "y", "evaluate"),
        Cell("B", "new", 0, tmp_path / "z", "train"),
    ]
    got = expected_seconds(tmp_path, cells)
    overall, task_b = (1000 + 100 + 300) / 3, 300.0
    assert got["B/slow/seed0"] == pytest.approx(1000 * task_b / overall + 10.0)  # (the model's time, task-scaled)
    assert got["A/fast/seed1"] == pytest.approx(10.0)  # (an evaluation alone)
    assert "B/new/seed0" not in got  # (nothing to go by: the session's mean is used)


@pytest.mark.slow
def test_the_report_is_published_between_the_markers_of_the_results_page(resumed, tmp_path):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from publish_report import END, START, publish

    out = resumed[0]
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "results.md").write_text(f"# Results\n\nbefore\n\n{START}\nold\n{END}\n\nafter\n")
    text = publish(out, docs).read_text()
    assert text.startswith("# Results\n\nbefore\n") and text.rstrip().endswith("after") and "\nold\n" not in text
    assert "## The reproduction report" in text and "### Runs" in text and "\n## Runs" not in text
    assert "| BD5 | CM-CD-CLNN | 0 | not measured yet (not run) |" in text  # (every task of the benchmark)
    assert (
        "](figures/reproduction/fig3_errors.png)" in text and (docs / "figures/reproduction/fig3_errors.png").is_file()
    )
    assert "](runs/" not in text  # (links to run files, not committed, shown as paths)
    (docs / "results.md").write_text("# Results without markers\n")
    with pytest.raises(SystemExit, match="markers"):
        publish(out, docs)


@pytest.mark.slow  # (trains and evaluates one quick cell: about 10 s)
def test_a_reproduction_on_noisy_data_records_its_noise_and_sets_the_published_noise_runs_beside(tmp_path):
    import json

    out = tmp_path / "noisy"
    report = reproduce(["BP5-e"], ["CM-CD-CLNN"], [0], out, quick=True, jobs=1, noise=0.05, echo=lambda _: None)
    meta = json.loads((out / "data" / "BP5-e" / "meta.json").read_text())
    assert meta["request"]["noise"] == 0.05 and meta["request"]["noise_kind"] == "free"
    text = report.read_text()
    assert "**Noisy data**: observation noise of std 0.05" in text
    assert "## Table 2: learned μ, e (homogeneous tasks) on data with noise 0.05" in text
    row = next(line for line in text.splitlines() if line.startswith("| BP5-e (0, 1) |"))
    assert row.endswith(" / 0, 0.0373 |")  # (the published CM-CLNN at noise 0.05, H.6)
    with pytest.raises(ConfigError, match="holds a reproduction on data with noise 0.05: give another --out"):
        reproduce(["BP5-e"], ["CM-CD-CLNN"], [0], out, quick=True, noise=0.01)
    with pytest.raises(ConfigError, match="noise = -1.0 is not a finite number >= 0"):
        reproduce(["BP5-e"], ["CM-CD-CLNN"], [0], tmp_path / "other", quick=True, noise=-1.0)

"""The sample-efficiency sweep (diffcontact.eval.efficiency): one reproduction per training size, a table and a
figure beside the published curves."""

from __future__ import annotations

import json

import numpy as np
import pytest

from diffcontact.errors import ConfigError, DiffContactError
from diffcontact.eval import published
from diffcontact.eval.efficiency import cell_epochs, collect, efficiency_figure, efficiency_markdown, run_efficiency
from diffcontact.eval.reproduce import reproduce
from diffcontact.files import write_json
from diffcontact.run_dir import RunDir


def _evaluated(out, n, task, model, seed, mean, half):
    run = RunDir.of_cell(out / f"N{n}", task, model, seed)
    write_json(run.eval_dir() / "metrics.json", {"trajectory_error": {"steps": 5, "mean": mean, "ci95": half}})


def test_the_table_sets_each_measured_cell_beside_the_published_one_and_names_the_missing(tmp_path):
    _evaluated(tmp_path, 25, "Rope200", "CM-CD-CLNN", 0, 1.5e-4, 2e-5)
    _evaluated(tmp_path, 25, "Rope200", "CM-CD-CLNN", 1, 2.5e-4, 3e-5)
    _evaluated(tmp_path, 50, "Rope200", "MLP-CD-CLNN", 0, 9e-3, 1e-3)
    table = collect(tmp_path, "Rope200", ["CM-CD-CLNN", "MLP-CD-CLNN"], [25, 50], [0, 1])
    cm = table["CM-CD-CLNN"][25]
    assert cm is not None and cm["seeds"] == 2 and cm["mean"] == pytest.approx(2e-4)
    assert cm["ci95"] == pytest.approx(1.96 * np.std([1.5e-4, 2.5e-4], ddof=1) / 2**0.5)
    assert table["CM-CD-CLNN"][50] is None and table["MLP-CD-CLNN"][25] is None
    mlp = table["MLP-CD-CLNN"][50]
    assert mlp is not None and (mlp["mean"], mlp["ci95"], mlp["seeds"]) == (9e-3, 1e-3, 1)  # (one seed: its own)
    text = efficiency_markdown("Rope200", table)
    rows = {line.split(" | ")[0].strip("| "): line for line in text.splitlines() if line.startswith("| ")}
    assert "0.0002 ± 9.8e-05 (0.00192)" in rows["CM-CD-CLNN"]  # (published 1.915e-3 at N = 25)
    assert "not measured (0.00187)" in rows["CM-CD-CLNN"]
    assert "not measured (0.0296)" in rows["MLP-CD-CLNN"] and "0.009 ± 0.001 (0.0125)" in rows["MLP-CD-CLNN"]
    figure = efficiency_figure("Rope200", table, tmp_path / "efficiency.png")
    assert figure.stat().st_size > 1000


def test_bad_sizes_and_a_folder_of_another_training_size_are_refused(tmp_path):
    for sizes in ([], [0], [25, -1], [2.5], [True]):
        with pytest.raises(ConfigError, match="sizes"):
            run_efficiency("BP5-e", ["CM-CD-CLNN"], sizes, tmp_path)
    write_json(tmp_path / "reproduce.json", {"quick": True, "noise": 0.0, "n_train": 8, "sessions": []})
    with pytest.raises(ConfigError, match="8 training trajectories: give another --out for 12"):
        reproduce(["BP5-e"], ["CM-CD-CLNN"], [0], tmp_path, quick=True, n_train=12)
    with pytest.raises(ConfigError, match="n_train"):
        reproduce(["BP5-e"], ["CM-CD-CLNN"], [0], tmp_path / "other", quick=True, n_train=0)


def test_beyond_the_default_data_a_cell_trains_the_default_runs_optimiser_steps(tmp_path, monkeypatch):
    # the Rope200's default run: 600 epochs of 800 trajectories; N = 12,800 at 600 epochs would take 16 times its steps
    assert [cell_epochs("Rope200", "CM-CD-CLNN", n) for n in (25, 800, 1600, 3200, 12800)] == [None, None, 300, 150, 38]
    assert cell_epochs("Rope200", "IN-CP-SP", 6400) == 75 and cell_epochs("BP5-e", "MLP-CD-CLNN", 1000) == 160
    calls = []
    monkeypatch.setattr(
        "diffcontact.eval.reproduce.reproduce", lambda *a, **k: calls.append((k["n_train"], k["epochs"]))
    )
    run_efficiency("Rope200", ["CM-CD-CLNN", "IN-CP-SP"], [800, 3200], tmp_path, echo=lambda _: None)
    assert calls == [(800, {"CM-CD-CLNN": None, "IN-CP-SP": None}), (3200, {"CM-CD-CLNN": 150, "IN-CP-SP": 150})]
    record = json.loads((tmp_path / "efficiency.json").read_text())
    assert record["epochs_by_size"]["3200"] == {"CM-CD-CLNN": 150, "IN-CP-SP": 150}
    assert "- N = 3200: CM-CD-CLNN 150, IN-CP-SP 150" in (tmp_path / "efficiency.md").read_text()
    assert "N = 800:" not in (tmp_path / "efficiency.md").read_text()
    calls.clear()
    run_efficiency("Rope200", ["CM-CD-CLNN"], [3200], tmp_path, epochs=7, echo=lambda _: None)  # (given: every N)
    assert calls == [(3200, {"CM-CD-CLNN": 7})]
    with pytest.raises(ConfigError, match="epochs = 0 is not a whole number"):
        reproduce(["BP5-e"], ["CM-CD-CLNN"], [0], tmp_path / "bad", quick=True, epochs={"CM-CD-CLNN": 0})


@pytest.mark.slow  # (two quick cells: about 30 s)
def test_a_quick_sweep_trains_one_reproduction_per_size_and_resumes(tmp_path):
    table = run_efficiency("BP5-e", ["CM-CD-CLNN"], [12, 6], tmp_path, quick=True, echo=lambda _: None)
    assert sorted(table["CM-CD-CLNN"]) == [6, 12] and all(table["CM-CD-CLNN"].values())
    for n in (6, 12):
        meta = json.loads((tmp_path / f"N{n}" / "data" / "BP5-e" / "meta.json").read_text())
        assert meta["request"]["sizes"]["train"] == n  # (validation and test: quick mode's, for every N)
        assert json.loads((tmp_path / f"N{n}" / "reproduce.json").read_text())["n_train"] == n
    record = json.loads((tmp_path / "efficiency.json").read_text())
    assert record["sizes"] == [6, 12] and record["table"]["CM-CD-CLNN"]["6"]["seeds"] == 1
    assert (tmp_path / "efficiency.png").is_file() and "N = 6 | N = 12" in (tmp_path / "efficiency.md").read_text()
    learned = RunDir.of_cell(tmp_path / "N6", "BP5-e", "CM-CD-CLNN", 0).learned.stat().st_mtime
    run_efficiency("BP5-e", ["CM-CD-CLNN"], [6, 12], tmp_path, quick=True, echo=lambda _: None)
    assert RunDir.of_cell(tmp_path / "N6", "BP5-e", "CM-CD-CLNN", 0).learned.stat().st_mtime == learned
    assert published.SAMPLE_EFFICIENCY["Rope200"]["CM-CD-CLNN"][12800] == 1.202e-3


@pytest.mark.slow  # (a subprocess: the import of torch)
def test_python_dash_m_knows_every_command_the_console_script_knows():
    # `python -m diffcontact.cli` runs the module as __main__, which once started the app before the commands
    # defined below that point were registered ("No such command 'efficiency'")
    import subprocess
    import sys

    from typer.main import get_command

    from diffcontact.cli import app

    bench = set(get_command(app).commands["bench"].commands)  # type: ignore[attr-defined]
    done = subprocess.run(
        [sys.executable, "-m", "diffcontact.cli", "bench", "--help"], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert bench >= {"efficiency", "tosses", "train"} and all(name in done.stdout for name in bench)


def test_sweeps_run_apart_merge_into_one_table_later_cells_replacing_earlier(tmp_path, monkeypatch):
    import importlib.util
    import sys
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "efficiency_table", Path(__file__).parents[1] / "benchmarks" / "efficiency_table.py"
    )
    assert spec is not None and spec.loader is not None
    merger = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(merger)
    cell = {"mean": 1e-3, "ci95": 1e-4, "seeds": 1}
    first = {"task": "Rope200", "table": {"CM-CD-CLNN": {"25": cell, "1600": None}}}
    later = {
        "task": "Rope200",
        "table": {"CM-CD-CLNN": {"25": None, "1600": {**cell, "mean": 4e-4}}, "MLP-CD-CLNN": {"25": None}},
        "epochs_by_size": {"1600": {"CM-CD-CLNN": 300}},
    }
    write_json(tmp_path / "a" / "efficiency.json", first)
    write_json(tmp_path / "b.json", later)
    monkeypatch.setattr(sys, "argv", ["x", str(tmp_path / "a"), str(tmp_path / "b.json"), "--out", str(tmp_path / "m")])
    merger.main()
    merged = json.loads((tmp_path / "m" / "efficiency.json").read_text())
    assert merged["table"]["CM-CD-CLNN"] == {"25": cell, "1600": {**cell, "mean": 4e-4}}  # (None never replaces)
    assert merged["table"]["MLP-CD-CLNN"] == {"25": None} and merged["epochs_by_size"]["1600"] == {"CM-CD-CLNN": 300}
    text = (tmp_path / "m" / "efficiency.md").read_text()
    assert "0.0004 ± 0.0001 (0.00227)" in text and "- N = 1600: CM-CD-CLNN 300" in text
    assert (tmp_path / "m" / "efficiency.png").stat().st_size > 1000
    write_json(tmp_path / "c.json", {**first, "task": "Rope50"})
    with pytest.raises(DiffContactError, match="different tasks"):
        merger.merge([first, json.loads((tmp_path / "c.json").read_text())])

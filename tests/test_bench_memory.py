"""`diffcontact bench memory`: the report's structure on a tiny case (no timing, no memory threshold asserted)."""

from __future__ import annotations

import json

import pytest

from diffcontact.bench.memory import COLUMNS, TABLE, run_memory_benchmark, summarize
from diffcontact.errors import ConfigError


def test_summarize_measures_the_growth_after_the_settling_epoch():
    rss = [100.0, 150.0, 160.0, 170.0, 200.0, 230.0, 260.0, 210.0]
    row = summarize(rss, settle=5, flat_mb=50.0)
    assert row == {
        "epochs": 8,
        "rss_epoch1_mb": 100.0,
        "rss_epoch5_mb": 200.0,
        "rss_last_mb": 210.0,
        "rss_max_mb": 260.0,
        "growth_mb": 60.0,
        "verdict": "grows",
    }
    assert summarize(rss[:6], settle=5, flat_mb=50.0)["verdict"] == "flat"
    short = summarize(rss[:2], settle=5)
    assert short["growth_mb"] is None and short["verdict"] == "too short"


def test_an_unknown_task_fails_before_any_training(tmp_path):
    with pytest.raises(ConfigError, match="NoSuchTask"):
        run_memory_benchmark(["NoSuchTask"], data=str(tmp_path), echo=lambda line: None)


@pytest.mark.slow
def test_the_report_of_a_tiny_run(tmp_path):
    """BP5-e, 2 epochs on a dataset of 8 training trajectories: one row with 2 RSS readings, JSON and table."""
    lines = []
    out = tmp_path / "memory.json"
    sizes = {"n_train": 8, "n_val": 4, "n_test": 4}
    result = run_memory_benchmark(["BP5-e"], 2, data=str(tmp_path / "data"), out=str(out), sizes=sizes,
                                  echo=lines.append)  # fmt: skip
    assert (tmp_path / "data" / "BP5-e" / "meta.json").is_file()  # generated as `diffcontact generate` does
    for key in ("diffcontact", "torch", "lightning", "python", "cpus", "threads"):
        assert key in result["header"]
    assert len(result["header"]["load_average_before"]) == 3 and len(result["header"]["load_average_after"]) == 3
    (row,) = result["rows"]
    assert row["task"] == "BP5-e" and row["epochs"] == 2 and len(row["rss_mb"]) == 2
    assert all(x > 0 for x in row["rss_mb"]) and row["rss_max_mb"] == max(row["rss_mb"])
    assert row["rss_epoch1_mb"] == row["rss_mb"][0] and row["rss_last_mb"] == row["rss_mb"][-1]
    assert set(COLUMNS) <= set(row) and row["verdict"] == "too short"  # (fewer epochs than the settling one)
    assert json.loads(out.read_text()) == result
    table = out.with_suffix(".md").read_text()
    assert TABLE in table and table.rstrip().endswith(lines[-1]) and lines[-1].startswith("| BP5-e | 2 |")

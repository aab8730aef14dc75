"""`diffcontact generate`: files, summary lines, skip on rerun, and clear errors for bad arguments."""

from __future__ import annotations

from typer.testing import CliRunner

from diffcontact.cli import app
from diffcontact.data import verify_dataset

SMALL = ["--n-train", "6", "--n-val", "3", "--n-test", "3", "--no-progress"]


def test_generate_writes_a_verified_dataset_and_skips_a_rerun(tmp_path):
    res = CliRunner().invoke(app, ["generate", "CP3-e", "--out", str(tmp_path), *SMALL])
    assert res.exit_code == 0, res.output
    assert "CP3-e train: 6 trajectories x 100 frames" in res.output and "chunks of 5" in res.output
    assert "CP3-e test:" in res.output and "done: 1 task(s)" in res.output
    meta = verify_dataset(tmp_path / "CP3-e")
    assert [meta["splits"][s]["n"] for s in ("train", "val", "test")] == [6, 3, 3]
    res = CliRunner().invoke(app, ["generate", "CP3-e", "--out", str(tmp_path), *SMALL])
    assert res.exit_code == 0 and "skipped" in res.output


def test_generate_bad_arguments(tmp_path):
    runner = CliRunner()
    res = runner.invoke(app, ["generate", "BP9", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "unknown task 'BP9'" in res.output
    res = runner.invoke(app, ["generate", "BP5", "--noise", "-0.5", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "noise = -0.5 is not a finite number >= 0" in res.output
    res = runner.invoke(app, ["generate", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "give either a TASK or --all" in res.output
    res = runner.invoke(app, ["generate", "BP5", "--all", "--out", str(tmp_path)])
    assert res.exit_code == 2
    assert not list(tmp_path.iterdir())

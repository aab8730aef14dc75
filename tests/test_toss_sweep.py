"""The training-size sweep on measured tosses: its cells, its resumption and its tables (on the shipped sample)."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from diffcontact.cli import app
from diffcontact.data.store import load_meta
from diffcontact.eval.toss_sweep import figure_points, sweep_figure


@pytest.mark.slow
def test_the_sweep_runs_its_cells_resumes_and_tabulates(tmp_path):
    out = tmp_path / "sweep"
    args = ["bench", "tosses", "sample", "--out", str(out), "-n", "4", "-n", "8", "-m", "nominal"]
    first = CliRunner().invoke(app, args)
    assert first.exit_code == 0, first.output
    record = json.loads((out / "sweep.json").read_text())
    cells = record["table"]["nominal"]
    assert set(cells) == {"4", "8"} and cells["4"] == cells["8"]  # (no training: the same test tosses, one score)
    assert 0 < cells["4"]["position_error_pct"] < 100 and cells["4"]["tosses"] == 2
    for n in (4, 8):  # (nested, seeded training subsets of one split; the validation and test tosses shared)
        request = load_meta(out / "data" / f"N{n}" / "CubeToss")["request"]
        assert request["train_tosses"] == n and request["first_state"]["flight_frames"] == 15
    ids = [load_meta(out / "data" / f"N{n}" / "CubeToss")["request"]["toss_ids"] for n in (4, 8)]
    assert set(ids[0]["train"]) < set(ids[1]["train"]) and ids[0]["test"] == ids[1]["test"]
    table = (out / "sweep.md").read_text()
    assert "| nominal |" in table and "N = 4" in table and (out / "sweep.png").stat().st_size > 0
    face = table.split("(`same_final_face`)")[1]  # (a count of tosses, as the cell's metrics.json has it)
    assert f"| nominal | {cells['4']['same_final_face']} | {cells['4']['same_final_face']} |" in face
    stamp = (out / "runs" / "nominal" / "eval" / "metrics.json").stat().st_mtime_ns
    again = CliRunner().invoke(app, args)  # (resumes: every cell is read, none run again)
    assert again.exit_code == 0 and (out / "runs" / "nominal" / "eval" / "metrics.json").stat().st_mtime_ns == stamp
    tables = CliRunner().invoke(app, [*args[:9], "-n", "16", "-m", "nominal,CM-CD-CLNN", "--tables"])
    assert tables.exit_code == 0, tables.output  # (runs nothing, imports nothing: the tables of what is scored)
    assert "3 cells not scored yet: N4 CM-CD-CLNN, N8 CM-CD-CLNN, N16 CM-CD-CLNN" in tables.output
    assert not (out / "runs" / "N4").exists() and not (out / "data" / "N16").exists()
    record = json.loads((out / "sweep.json").read_text())
    assert record["table"]["CM-CD-CLNN"] == {} and record["table"]["nominal"]["16"] == cells["4"]
    assert len(record["cells_not_scored"]) == 3 and "| CM-CD-CLNN | – | – | – |" in (out / "sweep.md").read_text()
    bad = CliRunner().invoke(app, [*args[:5], "-m", "drake"])
    assert bad.exit_code == 2 and "unknown methods ['drake']" in bad.output
    # the exact model set against each method toss by toss: here a "model" that predicts the recorded poses exactly
    import numpy as np

    from diffcontact.eval.toss_sweep import _paired, sweep_markdown
    from diffcontact.eval.tosses import recorded_tosses

    folder = out / "data" / "N4" / "CubeToss"
    tosses, _ = recorded_tosses(folder, "test")
    exact = out / "runs" / "N4" / "CM-CD-CLNN" / "eval"
    exact.mkdir(parents=True)
    np.savez(exact / "predictions.npz", position=tosses.position, quaternion=tosses.quaternion,
             offsets=tosses.offsets, toss_id=tosses.toss_id)  # fmt: skip
    paired = _paired(out, folder, ("CM-CD-CLNN", "nominal"), 4)
    assert paired["nominal"]["mean"] == pytest.approx(-cells["4"]["position_error_pct"], rel=1e-12)
    assert paired["nominal"]["lo"] <= paired["nominal"]["mean"] <= paired["nominal"]["hi"] < 0
    # predictions of other tosses are refused, naming the file
    from diffcontact.errors import DatasetError
    from diffcontact.eval.tosses import paired_position_errors

    other = out / "other.npz"
    np.savez(other, position=tosses.position, toss_id=tosses.toss_id[::-1])
    with pytest.raises(DatasetError, match="other.npz holds predictions of other tosses"):
        paired_position_errors(folder, exact / "predictions.npz", {"other": other})
    # several references (a model's seeds): each toss's mean over them, here the exact tosses' 0 and the nominal's error
    from diffcontact.eval.toss_sweep import _folders

    nominal = _folders(out, "nominal", 4)[1] / "predictions.npz"
    halves = paired_position_errors(folder, [exact / "predictions.npz", nominal], {"nominal": nominal})
    assert halves["nominal"]["mean"] == pytest.approx(paired["nominal"]["mean"] / 2, rel=1e-12)
    text = sweep_markdown(record["table"], {"nominal": {"4": paired["nominal"]}})
    assert "CM-CD-CLNN minus each method" in text and f"| nominal | {paired['nominal']['mean']:+.2f} [" in text


@pytest.mark.slow
def test_trained_cells_go_to_the_backend_and_a_failed_one_is_named_after_the_others_are_tabulated(
    tmp_path, monkeypatch
):
    import shutil

    import diffcontact.eval.backends as backends
    from diffcontact.errors import DiffContactError
    from diffcontact.eval.toss_sweep import toss_sweep

    out, asked = tmp_path / "sweep", []

    def runner(backend, folder, threads):  # (a backend that "trains" by copying the nominal cell's scores)
        assert backend.name == "local" and folder == out and threads == 3

        def run(cell, data, quick):
            asked.append((cell.model, cell.todo, cell.pictures, cell.epochs, data.name, quick))
            if cell.model == "IN-CP-CLNN":
                return {"status": "failed", "error": "exited with 1"}
            shutil.copytree(out / "runs" / "nominal" / "eval", cell.run / "eval")
            return {"status": "done"}

        return run

    monkeypatch.setattr(backends, "cell_runner", runner)
    methods = ("nominal", "CM-CD-CLNN", "IN-CP-CLNN")
    with pytest.raises(DiffContactError, match=r"1 cells of the sweep failed: N4 IN-CP-CLNN: DiffContactError: exited"):
        toss_sweep("sample", out, sizes=(4,), methods=methods, epochs=2, jobs=1, threads=3, echo=lambda _: None)
    assert sorted(asked) == [("CM-CD-CLNN", "train", False, 2, "CubeToss", False),
                             ("IN-CP-CLNN", "train", False, 2, "CubeToss", False)]  # fmt: skip
    record = json.loads((out / "sweep.json").read_text())
    assert set(record["table"]["CM-CD-CLNN"]) == {"4"} and record["table"]["IN-CP-CLNN"] == {}
    assert list(record["failed"]) == ["N4 IN-CP-CLNN"] and record["paired"]["nominal"]["4"]["mean"] == 0.0
    assert "| IN-CP-CLNN | – |" in (out / "sweep.md").read_text()
    asked.clear()  # (again: the finished cells are read, only the failed one runs)
    with pytest.raises(DiffContactError):
        toss_sweep("sample", out, sizes=(4,), methods=methods, epochs=2, jobs=1, threads=3, echo=lambda _: None)
    assert [a[0] for a in asked] == ["IN-CP-CLNN"]


def test_the_figure_draws_diverged_cells_as_marks_not_values(tmp_path):
    table = {
        "CM-CD-CLNN": {"16": {"position_error_pct": 9.9}, "8": {"position_error_pct": 9.8}},
        "MLP-CD-CLNN": {"8": {"position_error_pct": 7.4e140}, "16": {"position_error_pct": 88.0}},
        "IN-CP-CLNN": {"8": {"position_error_pct": float("inf")}},
    }
    points = figure_points(table)
    assert points["CM-CD-CLNN"] == ([(8, 9.8), (16, 9.9)], [])  # (sorted by N, as numbers, not text)
    assert points["MLP-CD-CLNN"] == ([(16, 88.0)], [8]) and points["IN-CP-CLNN"] == ([], [8])
    assert sweep_figure(table, tmp_path / "sweep.png").stat().st_size > 0

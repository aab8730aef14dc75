"""A training run end to end on a tiny generated dataset: run directory, learned.json, resume, errors."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

import diffcontact as dc
from diffcontact.data.generate import generate_dataset
from diffcontact.data.store import load_split
from diffcontact.errors import ConfigError
from diffcontact.models import build_model
from diffcontact.solver import Status
from diffcontact.train.config import TrainConfig, resolve_preset, task_training
from diffcontact.train.module import KEEP_FAILED, ContactLightningModule
from diffcontact.train.run import keeps_last_epoch, planned_epochs, summarize_run, train_run
from diffcontact.train.summary import learned_summary, slot_contacts


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    generate_dataset("BP1", root, n_train=16, n_val=4, n_test=4, progress=False)
    return root


def test_run_directory_and_learned_json(data_root, tmp_path):
    run = tmp_path / "run"
    summary = train_run("BP1", epochs=2, out=run, data_root=data_root, batch_size=8, progress=False)
    assert (run / "config.json").is_file() and (run / "checkpoints" / "last.ckpt").is_file()
    assert (run / "loss.png").stat().st_size > 0
    assert list((run / "logs" / "csv").rglob("metrics.csv")) and list((run / "logs" / "tb").rglob("events.*"))
    learned = json.loads((run / "learned.json").read_text())
    assert learned == json.loads(json.dumps(summary))
    for key in ("mu", "e", "mass_ratio"):
        item = learned[key]
        evidence = {"identifiable", "std_error", "bootstrap_error", "identified", "max_abs_error_identified"}
        assert set(item) == {"learned", "true", "max_abs_error"} | (evidence if key != "mass_ratio" else set())
        assert len(item["learned"]) == len(item["true"])
        err = max(abs(a - b) for a, b in zip(item["learned"], item["true"]))
        assert item["max_abs_error"] == pytest.approx(err)
    assert len(set(learned["mu"]["identifiable"])) == 1  # (homogeneous: one value, identified by any slot)
    assert len(set(learned["mu"]["std_error"])) == 1 and len(set(learned["evidence_chunks"])) == 1
    assert learned["evidence_chunks"][0] > 0
    # μ and e refined by Gauss-Newton after the epochs: kept only if the validation loss does not rise, and then in
    # their own checkpoint (after 2 epochs the slot is not identified at its refined value, so it goes back)
    refined = learned["refinement"]
    assert {"mu_before", "e_before", "iterations", "reverted", "val_loss_before", "val_loss_after"} <= set(refined)
    assert not refined["kept"] or refined["val_loss_after"] <= refined["val_loss_before"]
    changed = refined["kept"] and refined["iterations"] > 0
    assert Path(learned["best_checkpoint"]).name.startswith("refined-best-") == changed
    assert (learned["mu"]["learned"][0] != refined["mu_before"][0]) == changed
    assert len(learned["collisions"]) == len(learned["mu"]["true"]) and sum(learned["collisions"]) > 0
    assert learned["mu"]["true"][0] == pytest.approx(0.2) and learned["e"]["true"][0] == pytest.approx(0.8)
    config = json.loads((run / "config.json").read_text())
    assert config["args"]["task"] == "BP1" and "torch" in config["versions"]
    assert config["args"]["preset"] == "default" and config["args"]["lr"] == 1e-2  # (epochs given explicitly)
    assert config["args"]["epochs"] == 2 and config["args"]["schedule"] == "cosine"
    log = next((run / "logs" / "csv").rglob("metrics.csv")).read_text().splitlines()
    rates = [float(r["train/lr"]) for r in csv.DictReader(log)
             if r.get("train/lr")]  # fmt: skip
    assert rates[0] == pytest.approx(1e-2) and rates[1] == pytest.approx(0.5 * (1e-2 + 1e-4))  # cosine, halfway


def test_a_run_whose_solver_fails_saves_the_failed_problems(data_root, tmp_path, monkeypatch):
    """Failed contact problems are counted in learned.json and the first ones saved beside it, to be solved again,
    each once; a resumed run adds its own after the earlier ones, and ``summarize`` run twice adds none the second
    time."""
    import diffcontact.train.module as module
    from diffcontact.solver import ContactSolver, solve_cone_qp
    from diffcontact.solver.contact_solver import load_failed

    def first_element_fails(*args, **kw):  # (in every solver the training module builds)
        f, info = solve_cone_qp(*args, **kw)
        info.status[0] = Status.NUMERICAL
        return f, info

    monkeypatch.setattr(module, "ContactSolver", lambda **kw: ContactSolver(**kw, backend=first_element_fails))
    run = tmp_path / "run"
    learned = train_run(
        "BP1", epochs=1, out=run, data_root=data_root, batch_size=8, schedule="constant", progress=False
    )
    assert learned["solver_failures"] > 0 and learned["solver_failures_saved"] == "solver_failures.npz"
    saved = load_failed(run / "solver_failures.npz")
    # after training, the refinement of μ and e and the identification solve contact problems too: their failures
    # are counted apart, and kept after training's
    after = learned["solver_failures_after_training"]["NUMERICAL"]
    assert after > 0 and set(learned["solver_failures_after_training"]) == {"NUMERICAL"}
    # (the refinement meets some problems more than once: each is kept once)
    assert distinct(saved) == len(saved) and 0 < len(saved) <= min(KEEP_FAILED, learned["solver_failures"] + after)
    assert all(int(p["status"]) == Status.NUMERICAL and p["A"].shape == (len(p["q"]),) * 2 for p in saved)
    again = train_run("BP1", epochs=2, out=run, data_root=data_root, batch_size=8, resume=True, progress=False)
    both = load_failed(run / "solver_failures.npz")
    assert again["solver_failures"] > learned["solver_failures"]
    assert distinct(both) == len(both) and len(saved) < len(both) <= KEEP_FAILED
    assert all(np.array_equal(a["A"], b["A"]) for a, b in zip(saved, both))
    summarize_run(run)
    once = load_failed(run / "solver_failures.npz")
    summarize_run(run)  # (the same checkpoint: the same problems fail again, and are kept once)
    assert len(load_failed(run / "solver_failures.npz")) == len(once) and distinct(once) == len(once)


def distinct(problems: list[dict]) -> int:
    """How many of saved failed problems differ in some array."""
    return len({tuple((k, p[k].tobytes()) for k in sorted(p)) for p in problems})


def test_resume_continues_to_more_epochs(data_root, tmp_path):
    run = tmp_path / "run"
    train_run("BP1", epochs=1, out=run, data_root=data_root, batch_size=8, schedule="constant", progress=False)
    summary = train_run("BP1", epochs=2, out=run, data_root=data_root, batch_size=8, resume=True, progress=False)
    assert summary["epochs_trained"] == 2


def test_bad_arguments_are_clear_errors(data_root, tmp_path):
    with pytest.raises(ConfigError, match="model = 'XX' is not one of"):
        train_run("BP1", "XX", epochs=1, out=tmp_path, data_root=data_root)
    with pytest.raises(ConfigError, match="epochs = 0 is not an integer >= 1"):
        train_run("BP1", epochs=0, out=tmp_path, data_root=data_root)
    with pytest.raises(ConfigError, match="no checkpoint to resume from"):
        train_run("BP1", epochs=1, out=tmp_path / "fresh", data_root=data_root, resume=True)
    with pytest.raises(ConfigError, match="preset = 'fast' is not one of"):
        train_run("BP1", preset="fast", out=tmp_path, data_root=data_root)


def test_presets_give_the_optimiser_settings_and_explicit_values_win():
    default = resolve_preset("default")
    assert (default["epochs"], default["lr"], default["schedule"], default["batch_size"]) == (200, 1e-2, "cosine", 50)
    assert default["coef_lr"] == pytest.approx(1 / 6)
    assert default["mu_transform"] == default["e_transform"] == "projected"
    published = resolve_preset("published", epochs=5)
    assert (published["epochs"], published["lr"], published["batch_size"]) == (5, 1e-3, 200)
    assert (published["mu_transform"], published["e_transform"]) == ("relu", "hardsigmoid")
    assert resolve_preset("default", lr=3e-3, schedule="constant", batch_size=None)["lr"] == 3e-3
    with pytest.raises(ConfigError, match="unknown settings"):
        resolve_preset("default", momentum=0.9)


def _task_file(tmp_path, training: str):
    text = (dc.config.tasks_dir() / "BP1.toml").read_text() + "\n[training]\n" + training
    path = tmp_path / "BP1.toml"
    path.write_text(text)
    return path


def test_task_file_training_table_adjusts_the_default_preset_only(tmp_path):
    path = _task_file(tmp_path, "mu_coef_lr = 1.0\nepochs = 7\n")
    own = task_training(path)
    assert own == {"mu_coef_lr": 1.0, "epochs": 7}
    assert resolve_preset("default", own)["mu_coef_lr"] == 1.0
    assert resolve_preset("default", own, epochs=3)["epochs"] == 3  # (an explicit value wins)
    assert resolve_preset("published", own)["epochs"] == 1000
    assert task_training("BP1") == {}
    with pytest.raises(ConfigError, match=r"training.momentum is not a training setting"):
        task_training(_task_file(tmp_path, "momentum = 0.9\n"))
    with pytest.raises(ConfigError, match=r"training.mu_coef_lr = -1 is not positive"):
        task_training(_task_file(tmp_path, "mu_coef_lr = -1.0\n"))
    assert task_training(_task_file(tmp_path, "mu_l1 = 0.0\n")) == {"mu_l1": 0.0}  # (no pull: allowed)
    with pytest.raises(ConfigError, match=r"training.mu_l1 = -1"):
        task_training(_task_file(tmp_path, "mu_l1 = -1.0\n"))
    assert task_training("BD5") == {"mu_coef_lr": 1.0, "mu_l1": 1e-5}


def test_a_small_dataset_trains_for_the_task_files_fewest_optimiser_steps(data_root, tmp_path):
    assert planned_epochs(30, 240, 8) == 30 and planned_epochs(30, 240, 1) == 240 and planned_epochs(3, 10, 4) == 3
    with pytest.raises(ConfigError, match=r"training.min_steps = -1"):
        task_training(_task_file(tmp_path, "min_steps = -1\n"))
    task = _task_file(tmp_path, "min_steps = 9\n")
    summary = train_run(str(task), epochs=1, out=tmp_path / "run", data_root=data_root, batch_size=1000,
                        schedule="constant", progress=False)  # fmt: skip
    # (one batch an epoch: the 16 training trajectories' chunks in one batch of 1000)
    assert summary["optimiser_steps"] == 9 and summary["epochs_trained"] == 9
    metrics = next((tmp_path / "run" / "logs" / "csv").rglob("metrics.csv")).read_text().splitlines()
    validated = [int(r["epoch"]) for r in csv.DictReader(metrics) if r.get("val/loss")]
    assert validated == [8], validated  # (every 9th epoch: one validation, as 1 epoch asked for would have)
    # resumed with the epochs it was asked for, the run is finished: its planned epochs, not 1, are the bound
    again = train_run(str(task), out=tmp_path / "run", data_root=data_root, resume=True, progress=False)
    assert again["epochs_trained"] == 9
    assert json.loads((tmp_path / "run" / "config.json").read_text())["args"]["min_steps"] == 9


def test_mu_and_e_can_start_from_a_scan_of_the_training_loss(data_root, tmp_path):
    with pytest.raises(ConfigError, match=r"coef_start = 'best' is not one of \['random', 'scan'\]"):
        train_run(str(_task_file(tmp_path, 'coef_start = "best"\n')), epochs=1, out=tmp_path / "bad",
                  data_root=data_root, progress=False)  # fmt: skip
    task = _task_file(tmp_path, 'coef_start = "scan"\npotential = "known"\n')  # (a random potential would blur it)
    summary = train_run(str(task), epochs=1, out=tmp_path / "run", data_root=data_root, batch_size=8, progress=False)
    record = json.loads((tmp_path / "run" / "coef_start.json").read_text())
    assert len(record["grid"]) == 16 and record["windows"] == min(
        64, len(load_split(data_root / "BP1", "train").chunk_x)
    )
    least = min(record["grid"], key=lambda c: c["loss"])
    assert record["chosen"] == {"mu": least["mu"], "e": least["e"]} == summary["coef_start"]
    # BP1's ball bounces at e = 0.8 with μ = 0.2: the least loss is at the e next to it, and at a μ above 0.2 as
    # well as at it (μ = 0.3 and 0.6 differ by 2 %: a ball that sticks on these bounces is as good as one at 0.2)
    assert least["e"] == 0.85 and least["mu"] >= 0.15, record["grid"]


def test_mu_learns_at_its_own_rate_where_given():
    def rates(**kw):
        module = ContactLightningModule(TrainConfig("BP1", lr=1e-2, coef_lr=0.5, schedule="constant", **kw))
        module.trainer = None
        return [g["lr"] for g in module.configure_optimizers().param_groups]

    assert rates() == pytest.approx([1e-2, 5e-3, 5e-3])  # (others, μ, e)
    assert rates(mu_coef_lr=1.0) == pytest.approx([1e-2, 1e-2, 5e-3])


def _summary(task: str):
    module = ContactLightningModule(TrainConfig(task))
    state = module.task.sample(2, seed=0)  # (no contact)
    chunk_x, chunk_v = (t[:, None].expand(-1, 2, -1, -1) for t in (state.x, state.v))
    return module, learned_summary(module.net, module.task, chunk_x, chunk_v)


def test_learned_json_reports_the_moments_of_extended_bodies():
    module, summary = _summary("BD1")  # one disk: second moments per unit mass r²/4 per axis
    truth = module.task.params.inertia.moments.flatten().tolist()
    assert summary["moments"]["true"] == truth and len(summary["moments"]["learned"]) == len(truth)
    assert "moments" not in _summary("BP1")[1]  # point masses


def _ball_chunks(task, starts):
    """Two-frame chunks of BP1 simulated from (x, y, vx, vy) starts: (N, 2, 1, 2) each."""
    from diffcontact.state import State

    s = torch.tensor(starts, dtype=torch.float64)
    xs, vs, _ = dc.simulator_for(task).rollout(State(s[:, None, :2], s[:, None, 2:]), task.params, task.dt, 2)
    return xs, vs


def test_collisions_that_identify_mu_and_e_are_counted_per_slot(data_root):
    """BP1 (μ = 0.2, e = 0.8, ball radius 0.1, floor y = 0): a fast impact with a large tangential speed slides
    (Δv_t ≤ μ(1 + e)·2 m/s < 3 m/s), a head-on one does not; both bounce as e sets (e·v_n far above the
    compensation's target); with e = 0.05 and a 3 cm penetration the target velocity (0.125·0.03/0.01 = 0.38 m/s)
    exceeds e·v_n and e has no effect.  A chunk without contact identifies nothing; the dataset's collisions are its
    active candidates; the rope's limits have no tangent."""
    import dataclasses

    from diffcontact.data.store import load_split

    task = dc.build_task("BP1")
    floor = 1  # (slot of the wall y >= 0)
    xs, vs = _ball_chunks(task, [[0.5, 0.105, 3.0, -2.0], [0.5, 0.105, 0.0, -2.0], [0.5, 0.5, 0.0, 0.0]])
    counts = slot_contacts(task, xs, vs)
    assert counts["collisions"].tolist() == [0, 2, 0, 0]
    assert counts["slipping"][floor] == 1 and counts["bound"][floor] == 2
    weak = dataclasses.replace(task, params=dataclasses.replace(task.params, e=torch.full_like(task.params.e, 0.05)))
    xs, vs = _ball_chunks(weak, [[0.5, 0.105, 0.0, -2.5]])
    counts = slot_contacts(weak, xs, vs)
    assert counts["collisions"][floor] == 1 and counts["bound"].sum() == 0
    split = load_split(data_root / "BP1", "train")
    counts = slot_contacts(task, split.chunk_x, split.chunk_v)
    gaps = task.system.detector.gaps(split.chunk_x[:, 1:].flatten(0, 1).double())
    assert counts["collisions"].sum() == (gaps < 0).sum() > 0
    _, quiet = _summary("BP1")
    assert quiet["e"]["max_abs_error"] is None and quiet["e"]["identifiable"] == [False] * len(quiet["e"]["true"])
    rope = dc.build_task("Rope")
    state = rope.sample(8, seed=0)
    x = 1.5 * state.x  # (every link stretched by 1.5, beyond its limit 1.2: all in contact)
    counts = slot_contacts(rope, torch.stack([x, x], 1), torch.stack([state.v, state.v], 1))
    assert counts["collisions"].sum() >= 8 * 10 and counts["slipping"].sum() == 0


def test_inertia_is_compared_up_to_the_scale_a_learned_potential_absorbs():
    """Closed forms: the gyroscope's per-axis second moments J are identified only up to J → s(J + r²) − r² (its
    principal moments about the joint, r = the centre's offset 0.5 m along e3); a disk's two second moments only
    through their sum; any other change shows as the ratio it makes."""
    from diffcontact import build_task
    from diffcontact.state import Inertia
    from diffcontact.train.summary import inertia_spread

    gyro = build_task("Gyro")
    x, true = gyro.sample(8, seed=0).x, gyro.params.inertia
    r2 = torch.tensor([0.0, 0.0, 0.25], dtype=torch.float64)
    same = Inertia(7 * true.masses, 3.075 * (true.moments + r2) - r2)
    assert inertia_spread(gyro.system, same, true, x)["spread"] < 1e-7
    wider = Inertia(true.masses, true.moments * torch.tensor([1.25, 1.0, 1.0], dtype=torch.float64))
    assert inertia_spread(gyro.system, wider, true, x)["spread"] == pytest.approx(0.125, rel=1e-6)  # I_3: 0.54/0.48
    disks = build_task("BD5")
    x, true = disks.sample(8, seed=0).x, disks.params.inertia
    split = true.moments + torch.tensor([1e-3, -1e-3], dtype=torch.float64)
    assert inertia_spread(disks.system, Inertia(2 * true.masses, split), true, x)["spread"] < 1e-9
    heavier = true.moments.clone()
    heavier[0] *= 1.1
    assert inertia_spread(disks.system, Inertia(true.masses, heavier), true, x)["spread"] == pytest.approx(0.1)


def test_summarize_recomputes_learned_json_and_keeps_the_counters(data_root, tmp_path):
    from diffcontact.train.run import summarize_run

    run = tmp_path / "run"
    train_run("BP1", epochs=1, out=run, data_root=data_root, batch_size=8, progress=False)
    learned = json.loads((run / "learned.json").read_text())
    stale = {k: v for k, v in learned.items() if not k.startswith("collisions") and k != "inertia"}
    (run / "learned.json").write_text(json.dumps(stale))
    assert summarize_run(run) == json.loads((run / "learned.json").read_text()) == learned
    # a run trained before the refinement: summarize refines it as training would have
    best = Path(learned["best_checkpoint"])
    older = {k: v for k, v in stale.items() if k != "refinement"}
    older["best_checkpoint"] = str(best.with_name(best.name.removeprefix("refined-")))
    if best.name.startswith("refined-"):
        best.unlink()
    (run / "learned.json").write_text(json.dumps(older))
    again = summarize_run(run)
    assert again["best_checkpoint"] == learned["best_checkpoint"] and Path(again["best_checkpoint"]).is_file()
    assert again["mu"]["learned"] == learned["mu"]["learned"] and again["refinement"] == learned["refinement"] | {
        "seconds": again["refinement"]["seconds"]
    }
    moved = tmp_path / "moved"
    run.rename(moved)  # (the checkpoint path recorded is the old one: the run's own folder is used)
    assert summarize_run(moved)["mu"] == learned["mu"]
    from typer.testing import CliRunner

    from diffcontact.cli import app

    result = CliRunner().invoke(app, ["summarize", str(moved)])  # (prints what was learned and its error)
    assert result.exit_code == 0, result.output
    shown = json.loads(result.output)
    assert shown["mu"] == {"learned": learned["mu"]["learned"], "max_abs_error": learned["mu"]["max_abs_error"]}
    for ckpt in (moved / "checkpoints").glob("*best*"):
        ckpt.unlink()
    with pytest.raises(ConfigError, match="best checkpoint .* is missing"):
        summarize_run(moved)
    with pytest.raises(ConfigError, match="not a finished training run"):
        summarize_run(tmp_path / "nothing")


def test_the_mu_pull_is_checked_and_recorded():
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match=r"mu_l1 = .* is not a finite number >= 0"):
            TrainConfig.resolve("BP1", mu_l1=bad)
    assert TrainConfig.resolve("BP1", mu_l1=0.0).mu_l1 == 0.0
    assert resolve_preset("default", task_training("BD5"))["mu_l1"] == 1e-5
    assert resolve_preset("default")["mu_l1"] == resolve_preset("published")["mu_l1"] == 0.0


def test_one_config_holds_every_setting_validated_and_the_module_takes_its_defaults():
    published = TrainConfig.resolve("BP1", preset="published")  # (every setting, also those the preset leaves alone)
    assert (published.lr, published.schedule, published.axis_scale, published.min_steps) == (1e-3, "constant", 1.0, 0)
    assert TrainConfig.from_record(published.record()) == published
    for bad, match in (
        (dict(model="CM-XX"), r"model = 'CM-XX' is not one of"),
        (dict(lr=0.0), r"lr = 0.0 is not a finite number > 0"),
        (dict(batch_size=0), r"batch_size = 0 is not an integer >= 1"),
        (dict(schedule="step"), r"schedule = 'step' is not one of \['constant', 'cosine'\]"),
        (dict(dtype="float16"), r"dtype = 'float16' is not one of"),
        (dict(model="CM-CD-CLNN", reg=0.1), r"reg = 0.1 is for the regularised models"),
        (dict(momentum=0.9), r"unknown training settings \['momentum'\]"),
    ):
        with pytest.raises(ConfigError, match=match):
            TrainConfig.resolve("BP1", **bad)
    assert TrainConfig.resolve("BP1", "CMr-CD-CLNN").reg > 0 and TrainConfig.resolve("BP1").reg == 0.0
    with pytest.raises(ConfigError, match=r"lacks \['lr'\]"):
        TrainConfig.from_record({k: v for k, v in published.record().items() if k != "lr"})
    config = TrainConfig.resolve("BP1", hidden=8, layers=1)
    module = ContactLightningModule(config)  # (the run's settings are the module's one settings argument)
    assert module.config is config and ContactLightningModule(config.record()).config == config
    with pytest.raises(TypeError, match=r"config is a TrainConfig or its record, not 'BP1'"):
        ContactLightningModule("BP1")  # type: ignore[arg-type]


def test_a_checkpoint_loads_with_its_settings_also_one_written_before_the_record(tmp_path):
    """A checkpoint holds its run's TrainConfig; one written when the module took keyword arguments holds the task,
    the model and the settings given, and loads with TrainConfig's defaults for the rest."""
    config = TrainConfig("BP1", "CMr-CD-CLNN", hidden=8, layers=1, seed=3, reg=0.05, lr=3e-3)
    module = ContactLightningModule(config)
    with torch.no_grad():
        module.learned.mu_raw.add_(0.25)  # (weights that a fresh module of the same seed does not have)
    state = module.state_dict()
    counters = {"skipped_steps": 2, "forward_failures": 1, "solver_failures_by_status": {}, "seconds": 9.0}
    for hyper in ({"config": config.record()}, {"task": "BP1", "model": "CMr-CD-CLNN", "hidden": 8, "layers": 1,
                                                 "seed": 3, "reg": 0.05, "lr": 3e-3}):  # fmt: skip
        path = tmp_path / "run.ckpt"
        torch.save({"hyper_parameters": hyper, "state_dict": state, "counters": counters}, path)
        loaded = ContactLightningModule.from_checkpoint(path)
        assert loaded.config == config and loaded.skipped_steps == 2 and loaded.seconds_before == 9.0
        assert all(torch.equal(v, loaded.state_dict()[k]) for k, v in state.items())


def test_a_baseline_weighs_velocities_whatever_the_tasks_setting_for_the_contact_models(data_root, tmp_path):
    """A task's velocity_weight = 0 (the real cube's, for the contact models' windows) would leave MLP-CD-CLNN's
    velocity jump without a gradient on one-step pairs: the jump moves no position within its step."""
    task = _task_file(tmp_path, "velocity_weight = 0.0\n")
    train_run(str(task), "MLP-CD-CLNN", epochs=1, out=tmp_path / "mlp", data_root=data_root, batch_size=64,
              progress=False)  # fmt: skip
    train_run(str(task), epochs=1, out=tmp_path / "cm", data_root=data_root, batch_size=64, progress=False)
    config = {r: json.loads((tmp_path / r / "config.json").read_text())["args"] for r in ("mlp", "cm")}
    assert {r: c["velocity_weight"] for r, c in config.items()} == {"mlp": 1.0, "cm": 0.0}
    net = build_model(dc.build_task("BP1"), "MLP-CD-CLNN", hidden=16, layers=1)
    x, v = torch.randn(4, 1, 2, dtype=torch.float64), torch.randn(4, 1, 2, dtype=torch.float64)
    x[:, :, 1] = -5.0  # (the ball far below the floor: the jump applies)
    px, pv = net(x, v, 2)
    assert torch.autograd.grad(px.sum(), net.jump[0].weight, allow_unused=True)[0] is None  # (positions: no gradient)
    assert torch.autograd.grad(pv.sum(), net.jump[0].weight)[0].abs().sum() > 0


def test_an_unknown_setting_is_refused_by_name_before_anything_is_loaded(tmp_path, monkeypatch):
    import diffcontact.train.run as run_module
    from diffcontact.train.config import GIVEN_SETTINGS

    def never(*args, **kwargs):
        raise AssertionError("the task file was read before the settings were checked")

    monkeypatch.setattr(run_module, "load_task", never)
    allowed = re.escape(str(sorted(GIVEN_SETTINGS)))
    with pytest.raises(ConfigError, match=rf"unknown training settings \['bacth_size'\]; allowed: {allowed}"):
        train_run("BP1", out=tmp_path / "run", data_root=tmp_path / "nowhere", bacth_size=8, progress=False)
    assert not (tmp_path / "run").exists()
    assert "batch_size" in GIVEN_SETTINGS and "task" not in GIVEN_SETTINGS and "first_state_lr" not in GIVEN_SETTINGS


def test_a_gpu_is_refused_with_its_reason(tmp_path):
    with pytest.raises(ConfigError, match=r"accelerator = 'gpu' is not one of \['cpu'\]: .* on the CPU"):
        train_run("BP1", out=tmp_path / "run", accelerator="gpu", progress=False)
    assert not (tmp_path / "run").exists()


def test_a_run_on_noisy_data_stops_when_its_validation_loss_stops_improving(data_root, tmp_path, monkeypatch):
    import diffcontact.train.run as run_module
    from diffcontact.train.run import stop_patience

    noisy = tmp_path / "noisy"
    generate_dataset("BP1", noisy, n_train=16, n_val=4, n_test=4, noise=0.05, progress=False)
    plain, first = TrainConfig(task="BP1"), TrainConfig(task="BP1", first_state_chunks=16, first_state_lr=0.005)
    assert stop_patience(noisy / "BP1", plain) == run_module.NOISY_PATIENCE
    assert stop_patience(data_root / "BP1", plain) is None and stop_patience(noisy / "BP1", first) is None
    monkeypatch.setattr(run_module, "NOISY_PATIENCE", 2)
    # (first states not learned: a run that learns them trains all its epochs)
    monkeypatch.setattr(run_module, "FIRST_STATE_LR", 0.0)
    run = tmp_path / "run"
    learned = train_run("BP1", epochs=40, out=run, data_root=noisy, batch_size=8, progress=False)
    with open(next((run / "logs" / "csv").rglob("metrics.csv"))) as fh:
        val = [float(r["val/loss"]) for r in csv.DictReader(fh) if r["val/loss"]]
    assert learned["early_stop"] == {"patience": 2, "stopped": True, "planned_epochs": 40}
    assert learned["epochs_trained"] == len(val) < 40
    assert min(val[-2:]) >= min(val[:-2])  # (stopped after 2 validations without a better loss ...)
    assert all(min(val[j - 1 : j + 1]) < min(val[: j - 1]) for j in range(2, len(val) - 1))  # (... and not before)
    clean = train_run("BP1", epochs=2, out=tmp_path / "clean", data_root=data_root, batch_size=8, progress=False)
    assert "early_stop" not in clean
    # the marking takes the recorded noise into account (a parametric bootstrap, train/identify.py); clean data: none
    assert all(b is not None for b in learned["e"]["bootstrap_error"]) and set(clean["e"]["bootstrap_error"]) == {None}
    # every chunk's first state is learned on noisy data, training and validation chunks, at 0.1 × the noise a step
    monkeypatch.setattr(run_module, "FIRST_STATE_LR", 0.1)
    learned = train_run("BP1", epochs=3, out=tmp_path / "first", data_root=noisy, batch_size=8, progress=False)
    args = json.loads((tmp_path / "first" / "config.json").read_text())["args"]
    assert (args["first_state_chunks"], args["first_state_val_chunks"]) == (16, 4)
    assert args["first_state_lr"] == pytest.approx(0.005)
    assert args["coef_lr"] == run_module.NOISY_COEF_LR  # (μ and e at the full rate on such a run ...)
    train_run("BP1", epochs=1, out=tmp_path / "given", data_root=noisy, batch_size=8, progress=False, coef_lr=0.5)
    assert json.loads((tmp_path / "given" / "config.json").read_text())["args"]["coef_lr"] == 0.5  # (... unless given)
    state = torch.load(tmp_path / "first" / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    assert state["first_train.steps"].tolist() == [3] * 16  # (each chunk moved once an epoch, in its batch)
    assert 0 < float(state["first_train.dx"].abs().max()) <= 0.005 * 3
    assert float(state["first_val.dx"].abs().max()) > 0
    assert "early_stop" not in learned and learned["epochs_trained"] == 3
    # (on free points the validation loss chooses its checkpoint; in a System's noise coordinates, its last epoch)
    system, chain = dc.build_task("BP1").system, dc.build_task("CP1-wall").system
    assert not keeps_last_epoch(TrainConfig(task="BP1", first_state_chunks=16), system)
    assert keeps_last_epoch(TrainConfig(task="CP1-wall", first_state_chunks=16), chain)
    assert not keeps_last_epoch(TrainConfig(task="CP1-wall"), chain)
    clean_args = json.loads((tmp_path / "clean" / "config.json").read_text())["args"]
    assert clean_args["first_state_chunks"] == clean_args["first_state_val_chunks"] == 0
    with pytest.raises(ConfigError, match=r"devices × num_nodes = 2: a run that learns its chunks' first states"):
        TrainConfig(task="BP1", first_state_chunks=16, devices=2)

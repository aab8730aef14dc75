"""A training run end to end on a tiny generated dataset: run directory, learned.json, resume, errors."""

from __future__ import annotations

import json

import pytest

from diffcontact.data.generate import generate_dataset
from diffcontact.errors import ConfigError
from diffcontact.train.module import ContactLightningModule
from diffcontact.train.run import learned_summary, resolve_preset, train_run


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
        assert set(item) == {"learned", "true", "max_abs_error"}
        assert len(item["learned"]) == len(item["true"])
        err = max(abs(a - b) for a, b in zip(item["learned"], item["true"]))
        assert item["max_abs_error"] == pytest.approx(err)
    assert learned["mu"]["true"][0] == pytest.approx(0.2) and learned["e"]["true"][0] == pytest.approx(0.8)
    config = json.loads((run / "config.json").read_text())
    assert config["args"]["task"] == "BP1" and "torch" in config["versions"]
    assert config["args"]["preset"] == "default" and config["args"]["lr"] == 1e-2  # (epochs given explicitly)
    assert config["args"]["epochs"] == 2


def test_resume_continues_to_more_epochs(data_root, tmp_path):
    run = tmp_path / "run"
    train_run("BP1", epochs=1, out=run, data_root=data_root, batch_size=8, progress=False)
    summary = train_run("BP1", epochs=2, out=run, data_root=data_root, batch_size=8, resume=True, progress=False)
    assert summary["epochs_trained"] == 2


def test_bad_arguments_are_clear_errors(data_root, tmp_path):
    with pytest.raises(ConfigError, match="model = 'XX' is not one of"):
        train_run("BP1", "XX", epochs=1, out=tmp_path, data_root=data_root)
    with pytest.raises(ConfigError, match="epochs = 0 is not >= 1"):
        train_run("BP1", epochs=0, out=tmp_path, data_root=data_root)
    with pytest.raises(ConfigError, match="no checkpoint to resume from"):
        train_run("BP1", epochs=1, out=tmp_path / "fresh", data_root=data_root, resume=True)
    with pytest.raises(ConfigError, match="preset = 'fast' is not one of"):
        train_run("BP1", preset="fast", out=tmp_path, data_root=data_root)


def test_presets_give_the_optimiser_settings_and_explicit_values_win():
    assert resolve_preset("default", None, None) == (200, 1e-2)
    assert resolve_preset("published", None, None) == (1000, 1e-3)
    assert resolve_preset("published", 5, None) == (5, 1e-3)
    assert resolve_preset("default", None, 3e-3) == (200, 3e-3)


def test_learned_json_reports_the_moments_of_extended_bodies():
    module = ContactLightningModule("BD1")  # one disk: second moments per unit mass r²/4 per axis
    summary = learned_summary(module)
    truth = module.task.params.inertia.moments.flatten().tolist()
    assert summary["moments"]["true"] == truth and len(summary["moments"]["learned"]) == len(truth)
    assert "moments" not in learned_summary(ContactLightningModule("BP1"))  # point masses

"""Dataset generation and storage: determinism, disjoint splits, metadata, skip, corruption, interrupted writes."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from diffcontact import files as files_mod
from diffcontact.config import load_task
from diffcontact.data import generate_dataset, load_split, verify_dataset
from diffcontact.data import store as store_mod
from diffcontact.data.store import ARRAYS, SPLITS
from diffcontact.errors import ConfigError, DatasetError

TASK = "CP3-e"
SMALL = dict(n_train=12, n_val=6, n_test=6, frames=30, progress=False, echo=None)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    meta = generate_dataset(TASK, root, **SMALL)
    return root / TASK, meta


def _copy(dataset, tmp_path):
    folder = tmp_path / TASK
    shutil.copytree(dataset[0], folder)
    return folder


def test_same_seed_gives_byte_identical_arrays(dataset, tmp_path):
    generate_dataset(TASK, tmp_path, **SMALL)
    for split in SPLITS:
        with np.load(dataset[0] / f"{split}.npz") as a, np.load(tmp_path / TASK / f"{split}.npz") as b:
            for key in ARRAYS:
                assert a[key].dtype == b[key].dtype and a[key].tobytes() == b[key].tobytes(), (split, key)


def test_splits_share_no_initial_state(dataset):
    starts = [load_split(dataset[0], s).x[:, 0].flatten(1).numpy() for s in SPLITS]
    rows = [set(map(bytes, map(np.ndarray.tobytes, s))) for s in starts]
    assert all(len(r) == len(s) for r, s in zip(rows, starts))  # no repeats inside a split either
    assert not (rows[0] & rows[1]) and not (rows[0] & rows[2]) and not (rows[1] & rows[2])


def test_metadata_records_config_seeds_versions_shapes_counts(dataset):
    folder, meta = dataset
    disk = json.loads((folder / "meta.json").read_text())
    assert disk["request"]["task"] == TASK and disk["request"]["contact_model"] == "CM"
    assert disk["request"]["config"] == store_mod.config_json(load_task(TASK))
    assert 'name = "CP3-e"' in disk["config_text"]
    assert disk["versions"]["torch"] and disk["versions"]["diffcontact"] and disk["versions"]["numpy"]
    assert [disk["splits"][s]["seed"] for s in SPLITS] == [0, 1, 2]
    for split, n in zip(SPLITS, (12, 6, 6)):
        info = disk["splits"][split]
        assert info["sha256"] == store_mod.sha256(folder / info["file"])
        assert info["arrays"]["x"]["shape"] == [n, 30, 3, 2] and info["arrays"]["chunk_x"]["shape"] == [n, 5, 3, 2]
        s = load_split(folder, split)
        assert info["chunks_with_collision"] == int(s.chunk_collision.sum())
        assert info["trajectories_with_collision"] == int(s.contact.any(1).sum())
        assert not s.contact[:, 0].any() and s.x.dtype == s.chunk_x.dtype
        assert np.array_equal(
            s.chunk_x.numpy(), s.x.numpy()[np.arange(n)[:, None], s.chunk_start.numpy()[:, None] + np.arange(5)]
        )
    assert sorted(p.name for p in folder.iterdir()) == ["meta.json", "test.npz", "train.npz", "val.npz"]


def test_identical_dataset_is_skipped_and_a_different_request_is_replaced_only_with_force(dataset, tmp_path):
    folder = _copy(dataset, tmp_path)
    before = {p.name: p.stat().st_mtime_ns for p in folder.iterdir()}
    assert generate_dataset(TASK, tmp_path, **SMALL)["skipped"]
    assert before == {p.name: p.stat().st_mtime_ns for p in folder.iterdir()}
    with pytest.raises(ConfigError, match=r"holds a dataset of another request \(sizes.test 6 -> 5\); replace it with"):
        generate_dataset(TASK, tmp_path, **{**SMALL, "n_test": 5})
    assert before == {p.name: p.stat().st_mtime_ns for p in folder.iterdir()}
    meta = generate_dataset(TASK, tmp_path, **{**SMALL, "n_test": 5}, force=True)
    assert not meta["skipped"] and load_split(folder, "test").n == 5
    # an invalid dataset with the same request is regenerated too, not reused
    with open(folder / "val.npz", "r+b") as fh:
        fh.truncate(100)
    assert not generate_dataset(TASK, tmp_path, **{**SMALL, "n_test": 5})["skipped"]
    verify_dataset(folder)


def test_truncated_or_edited_file_is_detected(dataset, tmp_path):
    folder = _copy(dataset, tmp_path)
    path = folder / "train.npz"
    good = path.read_bytes()
    data = bytearray(good)
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="train.npz: SHA-256 .* does not match"):
        load_split(folder, "train")
    path.write_bytes(good)
    with open(folder / "val.npz", "r+b") as fh:
        fh.truncate(1000)
    with pytest.raises(DatasetError, match="val.npz: SHA-256"):
        verify_dataset(folder)
    # a corrupt file whose checksum was also rewritten is still caught when it is read
    meta = json.loads((folder / "meta.json").read_text())
    meta["splits"]["val"]["sha256"] = store_mod.sha256(folder / "val.npz")
    (folder / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="val.npz is corrupt or incomplete"):
        load_split(folder, "val")
    # shapes that disagree with the metadata
    meta["splits"]["test"]["arrays"]["x"]["shape"][0] = 7
    (folder / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"array x is float64\[6, 30, 3, 2\], recorded float64\[7, 30, 3, 2\]"):
        load_split(folder, "test")
    (folder / "meta.json").write_text("{not json")
    with pytest.raises(DatasetError, match="meta.json is not valid JSON"):
        load_split(folder, "test")


def test_config_mismatch_is_detected(dataset):
    changed = load_task(TASK, overrides={"contact": {"cor": [0.5]}})
    with pytest.raises(DatasetError, match="generated from a different config of task 'CP3-e'"):
        load_split(dataset[0], "train", config=changed)
    with pytest.raises(DatasetError, match="split = 'dev' is not one of"):
        load_split(dataset[0], "dev")
    with pytest.raises(DatasetError, match="meta.json is missing"):
        load_split(dataset[0].parent / "nothing", "train")


def test_failure_between_write_and_rename_leaves_no_loadable_dataset(dataset, tmp_path, monkeypatch):
    folder = _copy(dataset, tmp_path)  # an existing valid dataset is being regenerated with other sizes
    real_replace = os.replace

    def failing_replace(src, dst):
        if str(dst).endswith("val.npz"):
            raise KeyboardInterrupt("interrupted")
        return real_replace(src, dst)

    monkeypatch.setattr(files_mod.os, "replace", failing_replace)
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(TASK, tmp_path, **{**SMALL, "n_val": 5}, force=True)
    monkeypatch.undo()
    assert not (folder / "meta.json").exists() and not list(folder.glob(".tmp-*"))
    for split in SPLITS:
        with pytest.raises(DatasetError, match="meta.json is missing"):
            load_split(folder, split)


_WRITER = """
import sys, numpy as np
from diffcontact.files import save_arrays
save_arrays(sys.argv[1], {"x": np.ones((64, 1024, 1024))})  # 512 MB
"""


@pytest.mark.slow
def test_killed_writer_leaves_no_file_that_loads(tmp_path):
    folder = tmp_path / TASK
    folder.mkdir()
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(folder / "train.npz")])
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not any(p.stat().st_size > 0 for p in folder.glob(".tmp-*")):
            time.sleep(0.002)
        assert proc.poll() is None, "the writer finished before it could be killed"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert not (folder / "train.npz").exists() and list(folder.glob(".tmp-*"))
    with pytest.raises(DatasetError, match="is not a complete dataset"):
        load_split(folder, "train")
    store_mod.remove_stale(folder)  # what the next generate does first
    assert not list(folder.iterdir())


def test_bad_arguments_are_clear_errors(tmp_path):
    with pytest.raises(ConfigError, match="unknown task 'BP9'"):
        generate_dataset("BP9", tmp_path, **SMALL)
    with pytest.raises(ConfigError, match="noise = -0.1 is not a finite number >= 0"):
        generate_dataset(TASK, tmp_path, **{**SMALL, "noise": -0.1})
    with pytest.raises(ConfigError, match="n_train = 0 is not an integer >= 1"):
        generate_dataset(TASK, tmp_path, **{**SMALL, "n_train": 0})
    with pytest.raises(ConfigError, match=r"seeds = \(0, 1, 1\) must be three different seeds"):
        generate_dataset(TASK, tmp_path, **SMALL, seeds=(0, 1, 1))
    with pytest.raises(ConfigError, match="chunk_len = 40 is larger than frames = 30"):
        generate_dataset(TASK, tmp_path, **SMALL, chunk_len=40)
    assert not list(tmp_path.iterdir())

"""Task-file validation at the boundary (issues 14, 19): unknown tables and keys, unsafe names, no bodies, huge
outputs; every packaged task file still loads and builds."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

import diffcontact as dc
from diffcontact.config import MAX_FRAMES, check_array_size, task_from_dict, tasks_dir
from diffcontact.data.generate import generate_dataset
from diffcontact.errors import ConfigError
from diffcontact.simulate import simulate_task


def _write(tmp_path: Path, base: str, edit) -> Path:
    """A copy of the packaged task ``base`` with ``edit(text) -> text`` applied, as tmp_path/task.toml."""
    path = tmp_path / "task.toml"
    path.write_text(edit((tasks_dir() / f"{base}.toml").read_text()))
    return path


@pytest.mark.parametrize("name", dc.available_tasks())
def test_every_packaged_task_file_loads_and_builds(name):
    task = dc.build_task(name)
    assert task.config.name == name and task.config.ref == name
    assert task.system.n_bodies >= 1


def test_a_typo_in_a_key_is_an_error_naming_key_table_and_allowed_keys(tmp_path):
    path = _write(tmp_path, "BP1", lambda t: t.replace("gravity = 9.81", "gravty = 9.8"))
    with pytest.raises(
        ConfigError, match=re.escape("potential.gravty is not a key of [potential]; allowed keys: gravity")
    ):
        dc.build_task(path)
    with pytest.raises(ConfigError, match=r"contact.cof is not a key of \[contact\]; allowed keys: mu, cor, "):
        dc.build_task("BP1", overrides={"contact": {"cof": [0.5]}})
    with pytest.raises(ConfigError, match=r"task.frame is not a key of \[task\]; allowed keys: name, system, dt"):
        dc.load_task("BP1", overrides={"task": {"frame": 10}})
    with pytest.raises(ConfigError, match=r"init.spin_mean is not a key of \[init\]; allowed keys: kind, box"):
        dc.build_task("BD1", overrides={"init": {"spin_mean": 1.0}})  # (a gyroscope key in a disk task)


def test_an_unknown_table_is_an_error_naming_the_allowed_tables(tmp_path):
    path = _write(tmp_path, "CP3", lambda t: t.replace("[potential]", "[potentail]"))
    with pytest.raises(ConfigError, match=r"\[potentail\] is not a table of a 'chain_pendulum' task; allowed tables: "):
        dc.build_task(path)
    with pytest.raises(ConfigError, match=r"\[pendulum\] is not a table of a 'gyroscope' task.*body, walls"):
        dc.build_task("Gyro", overrides={"pendulum": {"lengths": [1.0]}})


@pytest.mark.parametrize("name", ["../../x", "a/b", "..", ".hidden", "", "x" * 101, "tab\tname", "C:x"])
def test_an_unsafe_task_name_is_refused_before_anything_is_written(tmp_path, name):
    path = _write(tmp_path, "BP1", lambda t: t.replace('name = "BP1"', f"name = {name!r}"))
    message = "task.name is missing" if not name else r"task.name = .* is not a safe folder name"
    with pytest.raises(ConfigError, match=message):
        dc.build_task(path)
    out = tmp_path / "deep" / "out"
    with pytest.raises(ConfigError):
        generate_dataset(path, out, n_train=1, n_val=1, n_test=1, progress=False, echo=None)
    assert not (tmp_path / "x").exists() and not out.exists()


@pytest.mark.parametrize("base", ["BP1", "BD1", "CP2-ground"])
def test_zero_bodies_and_empty_masses_are_errors_naming_masses(tmp_path, base):
    with pytest.raises(ConfigError, match=r"bodies.masses is empty: at least one value is needed"):
        dc.build_task(base, overrides={"bodies": {"masses": [], "radii": []}})
    with pytest.raises(ConfigError, match=r"bodies.masses is empty"):
        dc.build_task(base, overrides={"bodies": {"masses": []}})  # (not "radii has 1 values, expected 0")


def test_a_huge_frames_is_bounded_and_a_huge_output_is_refused_with_its_size(tmp_path):
    with pytest.raises(
        ConfigError, match=rf"task.frames = 1000000000 is more than {MAX_FRAMES} \(a trajectory of 1e\+07 s\)"
    ):
        dc.load_task("BP1", overrides={"task": {"frames": 10**9}})
    assert dc.load_task("BP1", overrides={"task": {"frames": MAX_FRAMES}}).frames == MAX_FRAMES
    # 10^6 trajectories x 10^6 frames of BP5-e: 2 x 10^12 x 10 float64 values, 1.5e5 GiB, far above any machine's
    with pytest.raises(ConfigError, match=r"1000000 trajectories x 1000000 frames of BP5-e would hold 1.49e\+05 GiB"):
        simulate_task("BP5-e", 10**6, 10**6, 0, str(tmp_path / "x.npz"))
    with pytest.raises(ConfigError, match=r"800 trajectories x 1000000 frames of BP1 would hold 23.8 GiB"):
        check_array_size("800 trajectories x 1000000 frames of BP1", 2 * 800 * 10**6 * 2, limit=2**30)
    check_array_size("small", 10**6, limit=2**30)  # 8 MB: fine
    assert not (tmp_path / "x.npz").exists()


def test_three_dimensional_balls_and_their_errors():
    raw = {
        "task": {"name": "balls", "system": "bouncing", "dt": 0.01, "frames": 10},
        "bodies": {"kind": "point", "dim": 3, "masses": [0.1, 0.2], "radii": [0.1, 0.1]},
        "potential": {"gravity": 9.81},
        "contact": {"mu": [0.1], "cor": [0.8]},
    }
    task = dc.build_task(task_from_dict(raw))  # (the default walls: the unit cube)
    assert (task.system.d, task.system.n_slots, task.system.detector.count) == (3, 1 + 2 * 6, 13)
    s = task.sample(4, seed=0)
    assert s.x.shape == (4, 2, 3) and (task.system.detector.gaps(s.x) >= 0).all()
    x, v, hit = dc.simulator_for(task).rollout(s, task.params, task.dt, 40)
    assert hit.any() and (task.system.detector.gaps(x[:, -1]) > -0.02).all()  # (gravity along -z: they land)
    mgz = 9.81 * (torch.tensor([0.1, 0.2], dtype=torch.float64) * s.x[..., 2]).sum(-1)
    torch.testing.assert_close(task.params.potential_energy(s.x), mgz, rtol=1e-12, atol=0)  # (V = Σ m g z)
    energy = task.system.energy(task.params, x[:, -1], v[:, -1])
    assert (energy < task.system.energy(task.params, s.x, s.v)).all()  # (e = 0.8 < 1: every landing loses energy)
    with pytest.raises(ConfigError, match=r"walls.lines is for 2-D bodies; in 3-D give walls.planes"):
        dc.build_task("BP1", overrides={"bodies": {"dim": 3}})
    with pytest.raises(ConfigError, match=r"bodies.dim = 3 is not 2 \(points or disks\) or 3 \(points: balls\)"):
        dc.build_task("BD1", overrides={"bodies": {"dim": 3}, "walls": {"planes": [[0, 0, 1, 0]]}})

"""Measured tosses: the box-toss metrics by hand, the importer on the shipped sample, and every bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from diffcontact.cli import app
from diffcontact.data.measured import GRAVITY, finite_difference_twist, first_states, import_tosses
from diffcontact.data.tosses import SAMPLE, Tosses, read_tosses
from diffcontact.errors import DatasetError
from diffcontact.eval.pose_metrics import box_toss_metrics, face_down, paired_difference, per_toss_position_error

HALF = 0.0524


def test_the_three_metrics_against_hand_computed_values():
    # two tosses, 2 and 1 frames; the width is 0.1048 m
    offsets = np.array([0, 2, 3])
    # the third frame's centre is 1.048 cm lower than a box resting on z = 0: its corners are 10 % of the width deep
    p = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, HALF - 0.01048]])
    ph = p + np.array([[0.1048, 0, 0], [0, 0, 0], [0, 0.0524, 0]])  # errors 100 %, 0 %, 50 %
    q = np.tile([1.0, 0, 0, 0], (3, 1))
    turn_x = [math.cos(math.pi / 8), math.sin(math.pi / 8), 0, 0]  # 45° about x
    qh = np.array([[1.0, 0, 0, 0], turn_x, [-1.0, 0, 0, 0]])  # 0°, 45°, 0° (−q is q)
    m = box_toss_metrics(ph, qh, p, q, offsets, [HALF] * 3, table_height=0.0)
    assert m["position_error_pct"] == pytest.approx(((100 + 0) / 2 + 50) / 2)
    assert m["rotation_error_deg"] == pytest.approx(((0 + 45) / 2 + 0) / 2)
    assert m["penetration_pct"] == pytest.approx(((0 + 0) / 2 + 10) / 2)
    assert (m["tosses"], m["frames"]) == (2, 3)
    # each toss's last frame: the first turned 30° about x (its −z face still down), the second turned over (180°)
    turn_30 = [math.cos(math.pi / 12), math.sin(math.pi / 12), 0, 0]
    m = box_toss_metrics(ph, np.array([[1.0, 0, 0, 0], turn_30, [1.0, 0, 0, 0]]), p, q, offsets, [HALF] * 3, 0.0)
    assert m["same_final_face"] == 2 and m["position_error_pct_other_face"] is None
    m = box_toss_metrics(ph, np.array([[1.0, 0, 0, 0], turn_30, [0.0, 1.0, 0, 0]]), p, q, offsets, [HALF] * 3, 0.0)
    assert m["same_final_face"] == 1
    assert m["position_error_pct_same_face"] == pytest.approx(50) and m["position_error_pct_other_face"] == 50
    tilted = np.array([math.cos(math.pi / 3), math.sin(math.pi / 3), 0, 0])  # 120° about x: +y up, −y down
    assert face_down(np.array([[1.0, 0, 0, 0], tilted, [0.0, 1.0, 0, 0]])).tolist() == [4, 2, 5]


def test_central_differences_are_exact_for_a_parabola_and_a_steady_spin():
    dt, n = 0.01, 7
    t = np.arange(n) * dt
    position = np.stack([0.3 * t, 0 * t, 1.0 + 0.5 * t - 4.9 * t**2], 1)
    angle = 2.0 * t  # 2 rad/s about the body z axis
    quaternion = np.stack([np.cos(angle / 2), 0 * t, 0 * t, np.sin(angle / 2)], 1)
    tosses = Tosses(position, quaternion, 0 * position, 0 * position, np.array([0, n]), np.array([0]), dt)
    velocity, omega = finite_difference_twist(tosses)
    exact = np.stack([0.3 + 0 * t, 0 * t, 0.5 - 9.8 * t], 1)
    assert np.abs(velocity - exact).max() <= 1e-12  # (the ends too: one-sided differences of second order)
    assert np.abs(omega - [0, 0, 2.0]).max() <= 1e-12


def _free_flight(t, spin, p0=(0.1, -0.2, 0.5), v0=(0.4, 0.1, 0.3)):
    """Poses (frames, 3), (frames, 4) of a cube in free flight: a parabola and a steady spin about (1, 2, 2)/3."""
    position = np.asarray(p0) + np.outer(t, v0) - np.outer(0.5 * GRAVITY * t**2, [0, 0, 1])
    angle, axis = spin * t, np.array([1.0, 2.0, 2.0]) / 3
    quaternion = np.concatenate([np.cos(angle / 2)[:, None], np.sin(angle / 2)[:, None] * axis], 1)
    return position, quaternion


def test_first_states_fit_a_free_flight_exactly_and_average_out_pose_noise():
    dt = 1 / 148
    t = np.arange(40) * dt  # (the cube falls from 0.5 m: 40 frames of free flight, of which 15 are fitted)
    position, quaternion = _free_flight(t, spin=6.0)
    tosses = Tosses(position, quaternion, 0 * position, 0 * position, np.array([0, 40]), np.array([0]), dt)
    p, v, w = first_states(tosses, 0.0, [HALF] * 3)
    assert np.abs(p - position[0]).max() <= 1e-12 and np.abs(v - [0.4, 0.1, 0.3]).max() <= 1e-10
    assert np.abs(w - 6.0 * np.array([1.0, 2.0, 2.0]) / 3).max() <= 1e-10
    # with 1 mm of noise on the positions, the fit is ~10 times nearer than the one-sided difference
    rng = np.random.default_rng(0)
    errors = []
    for _ in range(50):
        noisy = Tosses(position + rng.normal(0, 1e-3, position.shape), quaternion, 0 * position, 0 * position,
                       np.array([0, 40]), np.array([0]), dt)  # fmt: skip
        differenced = finite_difference_twist(noisy)[0][0]
        errors.append([np.linalg.norm(first_states(noisy, 0.0, [HALF] * 3)[1][0] - v[0]),
                       np.linalg.norm(differenced - v[0])])  # fmt: skip
    fitted, differenced = np.sqrt(np.mean(np.square(errors), 0))
    assert fitted < differenced / 5
    # a toss that starts on the table (its lowest corner within the clearance) keeps the recorded first frame
    resting = Tosses(position - [0, 0, 0.5 - HALF], quaternion[:1].repeat(40, 0), 0 * position, 0 * position,
                     np.array([0, 40]), np.array([0]), dt)  # fmt: skip
    p, v, _ = first_states(resting, 0.0, [HALF] * 3)
    assert np.array_equal(p[0], resting.position[0])
    assert np.allclose(v[0], finite_difference_twist(resting)[0][0])


def test_importing_the_shipped_sample(tmp_path):
    meta = import_tosses("sample", tmp_path / "ct", split=(0.5, 0.25, 0.25), seed=3)
    req = meta["request"]
    assert req["measured"] and req["source"]["sha256"] and req["units"]["length"] == "m"
    ids = req["toss_ids"]
    assert sorted(ids["train"] + ids["val"] + ids["test"]) == list(range(20))
    assert (len(ids["train"]), len(ids["val"]), len(ids["test"])) == (10, 5, 5)
    assert -0.003 < req["table_height_m"] < 0.0  # the data's table is 1-2 mm below z = 0
    with np.load(tmp_path / "ct" / "test.npz") as z:
        lengths = meta["splits"]["test"]["lengths"]
        assert z["x"].shape == (5, max(lengths), 4, 3)
    # the same seed gives the same split; the whole import is reproducible to the byte
    again = import_tosses("sample", tmp_path / "again", split=(0.5, 0.25, 0.25), seed=3)
    assert again["splits"]["train"]["sha256"] == meta["splits"]["train"]["sha256"]
    every = import_tosses("sample", tmp_path / "all", all_test=True)
    assert len(every["request"]["toss_ids"]["test"]) == 20 and set(every["splits"]) == {"test"}


def _write_npz(path, frames, offsets, toss_id):
    np.savez(path, frames=frames, offsets=offsets, toss_id=toss_id, length_scale_m=0.0524, dt=1 / 148)
    return path


@pytest.fixture
def sample_arrays():
    with np.load(SAMPLE) as z:
        o = z["offsets"][:4]
        return z["frames"][: o[-1]].copy(), o.copy(), z["toss_id"][:3].copy()


def _bad(tmp_path, frames, offsets, toss_id, match, **kw):
    src = _write_npz(tmp_path / "bad.npz", frames, offsets, toss_id)
    out = tmp_path / "out"
    with pytest.raises(DatasetError, match=match):
        import_tosses(src, out, **kw)
    assert not out.exists()  # nothing written


def test_a_non_finite_value_names_the_file_and_toss(tmp_path, sample_arrays):
    frames, o, ids = sample_arrays
    frames[o[1] + 5, 8] = np.nan
    _bad(tmp_path, frames, o, ids, r"bad.npz, toss 1: frame 5, column 8 is not finite")


def test_a_quaternion_not_of_unit_norm(tmp_path, sample_arrays):
    frames, o, ids = sample_arrays
    frames[o[2] + 3, 3:7] *= 1.01
    _bad(tmp_path, frames, o, ids, r"toss 2: frame 3 has a quaternion of norm 1.01")


def test_a_toss_shorter_than_the_window(tmp_path, sample_arrays):
    frames, o, ids = sample_arrays
    _bad(tmp_path, frames, o, ids, r"toss 0 has \d+ frames, shorter than the window \(500 frames\)", window=500)


def test_an_empty_split(tmp_path, sample_arrays):
    frames, o, ids = sample_arrays
    _bad(tmp_path, frames, o, ids, r"split val is empty", split=(0.6, 0.0, 0.4))


def test_files_in_neither_layout(tmp_path):
    not_npz = tmp_path / "x.npz"
    not_npz.write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match="x.npz is not a readable .npz"):
        read_tosses(not_npz)
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3))
    with pytest.raises(DatasetError, match=r"other.npz: lacks arrays \['frames', 'offsets', 'toss_id'\]"):
        read_tosses(other)
    folder = tmp_path / "pts"
    folder.mkdir()
    torch.save(torch.zeros(1, 10, 13, dtype=torch.float64), folder / "0.pt")
    with pytest.raises(DatasetError, match=r"0.pt: holds \[1, 10, 13\], expected a tensor \(1, T, 19\)"):
        read_tosses(folder)


def test_a_folder_of_pt_files_reads_as_the_npz(tmp_path, sample_arrays):
    frames, o, ids = sample_arrays
    folder = tmp_path / "tosses_processed"
    folder.mkdir()
    for i, k in enumerate(ids):
        t = np.zeros((1, o[i + 1] - o[i], 19))
        t[0, :, :13] = frames[o[i] : o[i + 1]]
        torch.save(torch.from_numpy(t), folder / f"{k}.pt")
    a = read_tosses(folder)
    b = read_tosses(_write_npz(tmp_path / "same.npz", frames, o, ids))
    for key in ("position", "quaternion", "velocity", "omega", "offsets", "toss_id"):
        assert np.array_equal(getattr(a, key), getattr(b, key))


@pytest.mark.slow
def test_the_import_and_nominal_evaluation_commands(tmp_path):
    from typer.testing import CliRunner

    runner = CliRunner()
    data = tmp_path / "CubeToss"
    res = runner.invoke(app, ["import", "contactnets", "sample", "--out", str(data), "--split", "0.8", "0.1", "0.1"])
    assert res.exit_code == 0, res.output
    out = tmp_path / "nominal"
    res = runner.invoke(app, ["evaluate", "CubeToss", "--nominal", "--data", str(data), "--out", str(out)])
    assert res.exit_code == 0 and res.output.strip().endswith(f"-> {out}"), res.output
    m = json.loads((out / "metrics.json").read_text())
    assert m["tosses"] == 2 and 0 < m["position_error_pct"] < 100 and m["penetration_pct"] < 2
    with np.load(out / "predictions.npz") as z:
        assert z["position"].shape == (m["frames"], 3) and z["quaternion"].shape == (m["frames"], 4)
        ids = json.loads((data / "meta.json").read_text())["request"]["toss_ids"]["test"]
        assert z["toss_id"].tolist() == ids
    assert (out / "tosses.png").is_file()


def test_two_methods_are_set_against_each_other_toss_by_toss():
    position = np.zeros((5, 3))
    hat = np.array([[0.0, 0.0, 0.1048], [0.0, 0.0, 0.0], [0.0524, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    errors = per_toss_position_error(hat, position, np.array([0, 2, 5]), [0.0524] * 3)
    assert errors == pytest.approx([50.0, 50.0 / 3])  # (one width in 2 frames; half a width in 3)
    same = paired_difference(errors, errors)
    assert (same["mean"], same["lo"], same["hi"], same["tosses"]) == (0.0, 0.0, 0.0, 2)
    shifted = paired_difference(errors + 1.5, errors)
    assert shifted["mean"] == shifted["lo"] == shifted["hi"] == pytest.approx(1.5)
    rng = np.random.default_rng(0)
    a = rng.normal(10.0, 1.0, 200)
    close, apart = paired_difference(a + rng.normal(0, 1, 200), a), paired_difference(a + 1.0, a - 1.0)
    assert close["lo"] < 0 < close["hi"] and apart["lo"] == pytest.approx(2.0)  # (holds 0; does not)
    b = a + rng.normal(0, 1, 200)
    assert paired_difference(a, b, seed=3) == paired_difference(a, b, seed=3)  # (seeded: the same interval)
    with pytest.raises(ValueError, match="paired errors"):
        paired_difference(a, a[:-1])

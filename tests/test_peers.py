"""The MuJoCo and Bullet cube peers: rollout layout, free flight against closed forms, a settling drop, an offset
centre of mass, the command.

Skipped for an engine (or the optimiser) that is not installed: ``pip install -e '.[peers]'``.
"""

from __future__ import annotations

import json
import os
import sys

import numpy as np
import pytest

from diffcontact.data.tosses import CONTACTNETS_DT, Tosses
from diffcontact.errors import ConfigError
from diffcontact.eval.pose_metrics import rotation_angle
from diffcontact.lock import output_lock
from diffcontact.peers import ENGINES, MissingPeerPackageError, load_engine
from diffcontact.peers.cube import COM_NAMES, COM_PARAMETERS, GRAVITY, HALF_EXTENT, SUBSTEPS, nominal
from diffcontact.systems.poses import box_vertices, rotate

TABLE = -0.00186  # m: the data's table plane, not at z = 0
SETTLE_TOL = 2e-3  # m: lowest corner of the resting cube from the table
REST_TOL = 1e-4  # m: how far a resting cube may move over its last frames
FLIGHT_TOL = 1e-6  # m: free flight against the semi-implicit Euler parabola
SPIN_TOL = 1e-9  # free rotation's quaternion against the constant angular momentum rotation's (≈ rad / 2)
COM = np.array([0.004, -0.003, 0.009])  # m: an offset centre of mass (body frame, from the box's centre)

pytestmark = pytest.mark.parametrize("name", list(ENGINES))


def _engine(name: str):
    pytest.importorskip(ENGINES[name])
    return load_engine(name)


def _tosses(states: list[np.ndarray], lengths: list[int]) -> Tosses:
    """Tosses whose first frame is each state (13,) (position, quaternion w first, velocity, body ω), the later
    frames copies of it (the peers read only frame 0 and the lengths)."""
    frames = np.concatenate([np.repeat(s[None], n, 0) for s, n in zip(states, lengths)])
    offsets = np.concatenate([[0], np.cumsum(lengths)])
    return Tosses(frames[:, 0:3], frames[:, 3:7], frames[:, 7:10], frames[:, 10:13], offsets,
                  np.arange(len(lengths)), CONTACTNETS_DT)  # fmt: skip


def _state(position, quaternion, velocity, omega) -> np.ndarray:
    q = np.asarray(quaternion, dtype=float)
    return np.concatenate([position, q / np.linalg.norm(q), velocity, omega]).astype(float)


def _quat_exp(rotvec: np.ndarray) -> np.ndarray:
    """Quaternions (F, 4) w first of rotation vectors (F, 3)."""
    angle = np.linalg.norm(rotvec, axis=1, keepdims=True)
    return np.concatenate([np.cos(angle / 2), 0.5 * np.sinc(angle / (2 * np.pi)) * rotvec], 1)


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, v1, w2, v2 = a[:, :1], a[:, 1:], b[:, :1], b[:, 1:]
    return np.concatenate([w1 * w2 - (v1 * v2).sum(1, keepdims=True), w1 * v2 + w2 * v1 + np.cross(v1, v2)], 1)


def test_rollout_has_one_frame_per_recorded_frame(name):
    engine = _engine(name)
    states = [_state([0.1, 0.0, 0.15], [1, 0.2, -0.1, 0.3], [0.5, -0.2, -1.0], [2.0, -1.0, 4.0]),
              _state([-0.3, 0.2, 0.08], [0.9, 0.0, 0.4, 0.0], [-0.3, 0.4, 0.0], [0.0, 3.0, 0.0])]  # fmt: skip
    tosses = _tosses(states, [5, 9])
    position, quaternion = engine.simulate(tosses, nominal(engine.PARAMETERS), TABLE)
    assert position.shape == (14, 3) and quaternion.shape == (14, 4)
    for i, s in enumerate(states):
        f = int(tosses.offsets[i])
        np.testing.assert_array_equal(position[f], s[0:3])
        np.testing.assert_array_equal(quaternion[f], s[3:7])
    np.testing.assert_allclose(np.linalg.norm(quaternion, axis=1), 1.0, atol=1e-9)
    assert not np.array_equal(position[1], position[0])  # (it moved)


def test_free_flight_is_a_parabola_and_a_constant_rotation(name):
    """No contact (1 m above the table): both engines integrate with semi-implicit Euler at h = dt / 10, whose
    exact free-flight solution is p0 + v0 t + ½ g t (t + h), the parabola shifted by ½ g h t (1.1e-4 m after 5
    frames); and with isotropic inertia ω is constant, so q(t) = exp(R ω_body t) q0."""
    engine = _engine(name)
    q0 = np.array([0.8, 0.3, -0.4, 0.2]) / np.linalg.norm([0.8, 0.3, -0.4, 0.2])
    state = _state([0.2, -0.1, 1.0], q0, [0.7, -0.4, 1.5], [3.0, -5.0, 2.0])
    frames = 6
    position, quaternion = engine.simulate(_tosses([state], [frames]), nominal(engine.PARAMETERS), TABLE)
    t = np.arange(frames)[:, None] * CONTACTNETS_DT
    h, g = CONTACTNETS_DT / SUBSTEPS, np.array([0.0, 0.0, -GRAVITY])
    euler = state[0:3] + state[7:10] * t + 0.5 * g * t * (t + h)
    np.testing.assert_allclose(position, euler, rtol=0, atol=FLIGHT_TOL)
    parabola = state[0:3] + state[7:10] * t + 0.5 * g * t**2
    assert np.abs(position - parabola).max() <= 0.5 * GRAVITY * h * t.max() + FLIGHT_TOL
    omega_world = rotate(q0[None], state[10:13][None])[0, 0]
    expected = _quat_mul(_quat_exp(omega_world * t), np.repeat(q0[None], frames, 0))
    sign = np.sign((quaternion * expected).sum(1, keepdims=True))  # (q and -q are the same rotation)
    np.testing.assert_allclose(quaternion, sign * expected, rtol=0, atol=SPIN_TOL)


def test_cube_dropped_flat_settles_on_the_table(name):
    engine = _engine(name)
    drop = _state([0.0, 0.0, TABLE + HALF_EXTENT + 0.01], [1, 0, 0, 0], [0, 0, 0], [0, 0, 0])
    frames = 148  # 1 s
    position, quaternion = engine.simulate(_tosses([drop], [frames]), nominal(engine.PARAMETERS), TABLE)
    lowest = (position[:, None] + rotate(quaternion, box_vertices([HALF_EXTENT] * 3)))[..., 2].min(1)
    assert np.abs(lowest[-30:] - TABLE).max() < SETTLE_TOL
    assert np.abs(position[-30:] - position[-1]).max() < REST_TOL
    assert rotation_angle(quaternion[-30:], quaternion[-1:].repeat(30, 0)).max() < REST_TOL / HALF_EXTENT


def test_a_rollout_the_engine_loses_is_not_returned_as_poses(name):
    engine = _engine(name)
    if name != "mujoco":
        pytest.skip("MuJoCo resets an unstable simulation and goes on; the others' states show the failure")
    ok = _state([0.0, 0.0, 0.3], [1, 0, 0, 0], [0.5, 0, 0], [0, 2, 0])
    lost = _state([0.0, 0.0, 0.3], [1, 0, 0, 0], [1e160, 0, 0], [0, 2, 0])  # (an acceleration MuJoCo calls unstable)
    tosses = _tosses([ok, lost, ok], [20, 20, 20])
    position, quaternion = engine.simulate(tosses, nominal(engine.PARAMETERS), TABLE)
    for i in (0, 2):  # (the tosses beside it are unaffected)
        assert np.isfinite(position[tosses.frames_of(i)]).all() and np.isfinite(quaternion[tosses.frames_of(i)]).all()
    np.testing.assert_array_equal(position[tosses.frames_of(0)], position[tosses.frames_of(2)])
    rows = tosses.frames_of(1)
    assert np.isfinite(position[rows.start]).all()  # (frame 0: the recorded pose)
    later = slice(rows.start + 1, rows.stop)
    assert np.isnan(position[later]).all() and np.isnan(quaternion[later]).all()


def _com(offset) -> dict[str, float]:
    return dict(zip(COM_NAMES, map(float, offset)))


def test_offset_centre_of_mass_flies_a_parabola(name):
    """Free flight with the centre of mass c off the box centre: the centre of mass p + R c follows the parabola of
    its initial state (p0 + R0 c, v0 + R0 (ω × c)), ω constant (isotropic inertia about it); the box centre does not
    (it circles the centre of mass: 2.9 mm off its own parabola here). Tolerance at time t: both engines' semi-implicit
    Euler at h = dt / 10 shifts the parabola by ½ g h t (as above), and Bullet integrates the centre of mass itself
    (FLIGHT_TOL from that shifted parabola). MuJoCo integrates the body frame's origin, the box centre, whose
    acceleration adds −ω × (ω × R c) to g: its left Riemann sum for the velocity is off by ≤ ½ h t |ω|³ |c|, the right
    sum of that velocity for the position by ≤ ½ h t |ω|² |c|, together ½ h t |ω|² |c| (1 + |ω| t) (≤ 1.0e-4 m
    here, 3.4e-5 seen)."""
    engine = _engine(name)
    q0 = np.array([0.8, 0.3, -0.4, 0.2]) / np.linalg.norm([0.8, 0.3, -0.4, 0.2])
    state = _state([0.2, -0.1, 1.0], q0, [0.7, -0.4, 1.5], [8.0, -12.0, 6.0])
    frames = 10
    position, quaternion = engine.simulate(_tosses([state], [frames]), nominal(engine.PARAMETERS) | _com(COM), TABLE)
    t = np.arange(frames)[:, None] * CONTACTNETS_DT
    h, g, w = CONTACTNETS_DT / SUBSTEPS, np.array([0.0, 0.0, -GRAVITY]), np.linalg.norm(state[10:13])
    arm, omega_world = rotate(q0[None], np.stack([COM, state[10:13]]))[0]  # R0 c, R0 ω
    p0, v0 = state[0:3] + arm, state[7:10] + np.cross(omega_world, arm)
    parabola = p0 + v0 * t + 0.5 * g * t**2
    origin_error = 0.5 * h * t * w**2 * np.linalg.norm(COM) * (1.0 + w * t) if name == "mujoco" else 0.0 * t
    tol = 0.5 * GRAVITY * h * t + origin_error + FLIGHT_TOL
    com = position + rotate(quaternion, COM[None])[:, 0]
    assert (np.linalg.norm(com - parabola, axis=1, keepdims=True) <= tol).all()
    euler, euler_tol = parabola + 0.5 * g * t * h, origin_error + FLIGHT_TOL  # (the integrators' own parabola)
    assert (np.linalg.norm(com - euler, axis=1, keepdims=True) <= euler_tol).all()
    centre_euler = state[0:3] + state[7:10] * t + 0.5 * g * t * (t + h)  # (where an ignored offset would put it)
    assert np.linalg.norm(position - centre_euler, axis=1).max() > 10 * euler_tol.max()
    expected = _quat_mul(_quat_exp(omega_world * t), np.repeat(q0[None], frames, 0))
    sign = np.sign((quaternion * expected).sum(1, keepdims=True))
    np.testing.assert_allclose(quaternion, sign * expected, rtol=0, atol=SPIN_TOL)


def test_offset_centre_of_mass_rests_on_a_face(name):
    """A cube standing still on its −z face with its centre of mass off the centre (inside the face's footprint)
    stays where it is: its box centre at the table's height plus a half-extent (to the engines' contact give) and
    its rotation unchanged. A box placed around the centre of mass, or the centre read back as the centre of mass,
    would be off by c (≥ 3 mm)."""
    engine = _engine(name)
    still = _state([0.05, -0.02, TABLE + HALF_EXTENT], [1, 0, 0, 0], [0, 0, 0], [0, 0, 0])
    frames = 148  # 1 s
    position, quaternion = engine.simulate(_tosses([still], [frames]), nominal(engine.PARAMETERS) | _com(COM), TABLE)
    assert np.abs(position - still[0:3]).max() < REST_TOL
    assert rotation_angle(quaternion, np.repeat(still[None, 3:7], frames, 0)).max() < REST_TOL / HALF_EXTENT
    assert np.abs(position[-30:] - position[-1]).max() < REST_TOL


def test_zero_centre_of_mass_offset_changes_nothing(name):
    """com_x, com_y, com_z = 0 roll out exactly as without them (the engines add exact zeros), in flight and in
    contact; they are checked like the others."""
    engine = _engine(name)
    states = [_state([0.1, 0.0, 0.15], [1, 0.2, -0.1, 0.3], [0.5, -0.2, -1.0], [2.0, -1.0, 4.0]),
              _state([-0.3, 0.2, 0.08], [0.9, 0.0, 0.4, 0.0], [-0.3, 0.4, 0.0], [0.0, 3.0, 0.0])]  # fmt: skip
    tosses, params = _tosses(states, [40, 25]), nominal(engine.PARAMETERS)
    without, zero = engine.simulate(tosses, params, TABLE), engine.simulate(tosses, params | _com([0, 0, 0]), TABLE)
    for a, b in zip(without, zero):
        np.testing.assert_array_equal(a, b)
    assert (without[0][:, 2] - TABLE < HALF_EXTENT * 1.5).any()  # (it met the table)
    assert [p.nominal for p in COM_PARAMETERS] == [0.0] * 3
    with pytest.raises(ConfigError, match=f"{name}: com_z = 0.05 is not in"):
        engine.simulate(tosses, params | {"com_z": 0.05}, TABLE)


def _npz(path, n: int = 10, length: int = 12) -> None:
    """A tiny tosses .npz in the ContactNets layout (frames in half-widths, ω in rad/s)."""
    rng = np.random.default_rng(3)
    frames = []
    for _ in range(n):
        q = rng.normal(size=4)
        start = _state([*rng.normal(size=2), 2.5], q, [*rng.normal(size=2), -2.0], rng.normal(size=3))
        toss = np.repeat(start[None], length, 0)
        toss[:, 2] -= np.linspace(0, 1.5, length)  # (a recorded fall; its values only enter the metrics)
        frames.append(toss)
    np.savez(path, frames=np.concatenate(frames), offsets=np.arange(n + 1) * length, toss_id=np.arange(n) + 100,
             length_scale_m=np.float64(HALF_EXTENT), dt=np.float64(CONTACTNETS_DT))  # fmt: skip


def test_fit_command_writes_its_files(name, tmp_path):
    _engine(name)
    pytest.importorskip("cma")
    from typer.testing import CliRunner

    from diffcontact.cli import app

    source, out = tmp_path / "tosses.npz", tmp_path / "fit"
    _npz(source)
    args = ["peers", "fit", name, str(source), "--out", str(out), "--budget", "2", "--split", "0.6", "0.2", "0.2"]
    result = CliRunner().invoke(app, [*args, "--train-tosses", "3", "--seed", "1", "--jobs", "2"])
    assert result.exit_code == 0, result.output
    fitted = json.loads((out / "fitted.json").read_text())
    metrics = json.loads((out / "metrics.json").read_text())
    assert fitted["train_tosses"] == 3 and fitted["optimiser"]["evaluations"] == 2 and fitted["seed"] == 1
    assert fitted["optimiser"]["jobs"] == 2
    assert set(fitted["parameters"]) == {p.name for p in load_engine(name).PARAMETERS} | set(COM_NAMES)
    for key in ("fitted", "nominal"):
        assert metrics[key]["tosses"] == 2 and np.isfinite(metrics[key]["position_error_pct"])
    with np.load(out / "predictions.npz") as z:
        assert z["position"].shape == (24, 3) and z["quaternion"].shape == (24, 4)
        assert z["toss_id"].tolist() == metrics["test_toss_id"] and z["offsets"].tolist() == [0, 12, 24]
    full = CliRunner().invoke(
        app,
        [*args[:4], "--out", str(tmp_path / "all"), *args[6:], "--seed", "1", "--twist", "poses"]
        + ["--no-centre-of-mass"],
    )
    assert full.exit_code == 0, full.output
    all_metrics = json.loads((tmp_path / "all" / "metrics.json").read_text())
    all_fitted = json.loads((tmp_path / "all" / "fitted.json").read_text())
    assert all_metrics["test_toss_id"] == metrics["test_toss_id"]  # (the same seed, the same test tosses)
    assert set(fitted["train_toss_id"]) < set(all_fitted["train_toss_id"]) and all_fitted["train_tosses"] == 6
    assert fitted["initial_twist"] == "fitted" and all_fitted["initial_twist"] == "poses"
    assert fitted["centre_of_mass"] and metrics["centre_of_mass"]  # (the default: com_* fitted too)
    assert not all_fitted["centre_of_mass"] and not all_metrics["centre_of_mass"]  # (--no-centre-of-mass)
    assert set(all_fitted["bounds"]) == set(all_fitted["parameters"])
    assert set(fitted["parameters"]) == set(fitted["bounds"]) == set(all_fitted["parameters"]) | set(COM_NAMES)
    assert all(abs(fitted["parameters"][n]) <= 0.02 for n in COM_NAMES)
    assert all_fitted["nominal_parameters"] == fitted["nominal_parameters"]  # (nominal: no offset)
    bad = CliRunner().invoke(app, [*args, "--train-tosses", "7"])  # (the training split holds 6)
    assert bad.exit_code == 2 and "train_tosses = 7 is not in [1, 6]" in bad.output
    bad = CliRunner().invoke(app, [*args, "--twist", "filtered"])
    assert bad.exit_code == 2 and "twist = 'filtered' is not one of fitted, recorded, poses" in bad.output
    held = tmp_path / "held"
    with output_lock(held):  # (another fit writing into the folder: this one stops at once and writes nothing)
        second = CliRunner().invoke(app, [*args[:4], "--out", str(held), *args[6:]])
        assert second.exit_code == 2 and f"{held} is being written by pid {os.getpid()}" in second.output
        assert [f.name for f in held.iterdir()] == [".lock"]


def test_candidates_scored_in_worker_processes_give_the_same_fit(name, tmp_path):
    engine = _engine(name)
    pytest.importorskip("cma")
    from diffcontact.data.tosses import read_tosses
    from diffcontact.peers.fit import fit_parameters

    _npz(tmp_path / "tosses.npz", n=4)
    tosses = read_tosses(tmp_path / "tosses.npz")
    fits = [fit_parameters(engine, tosses, TABLE, 40, 5, lambda s: None, jobs=jobs) for jobs in (1, 2)]
    assert fits[0]["params"] == fits[1]["params"] and fits[0]["train_metrics"] == fits[1]["train_metrics"]
    for a, b in zip(fits[0]["optimiser"]["history"], fits[1]["optimiser"]["history"], strict=True):
        assert {k: v for k, v in a.items() if k != "wall_time_s"} == {k: v for k, v in b.items() if k != "wall_time_s"}
    assert [f["optimiser"]["jobs"] for f in fits] == [1, 2] and len(fits[0]["optimiser"]["history"]) >= 2


def test_a_fit_whose_test_rollouts_the_engine_loses_says_so_and_writes_nothing(name, tmp_path, monkeypatch):
    engine = _engine(name)
    pytest.importorskip("cma")
    from typer.testing import CliRunner

    from diffcontact.cli import app

    simulate = engine.simulate

    def lose(tosses, params, table):  # (an engine that loses every rollout after its first frame)
        position, quaternion = simulate(tosses, params, table)
        later = np.ones(len(position), bool)
        later[tosses.offsets[:-1]] = False
        return np.where(later[:, None], np.nan, position), quaternion

    monkeypatch.setattr(engine, "simulate", lose)
    source, out = tmp_path / "tosses.npz", tmp_path / "fit"
    _npz(source)
    args = ["peers", "fit", name, str(source), "--out", str(out), "--budget", "2", "--jobs", "1"]  # (one process:
    result = CliRunner().invoke(app, args)  # the patched engine)
    assert result.exit_code == 2 and "rollouts of test tosses [" in result.output and "not finite" in result.output
    assert not (out / "metrics.json").exists() and not (out / "predictions.npz").exists()


def test_errors_name_the_engine_and_the_install(name, monkeypatch):
    with pytest.raises(ConfigError, match="engine 'drake' is not one of mujoco, bullet"):
        load_engine("drake")
    with monkeypatch.context() as m:
        m.setitem(sys.modules, ENGINES[name], None)  # (as if not installed)
        with pytest.raises(
            MissingPeerPackageError, match=rf"'{ENGINES[name]}', not installed: pip install -e '\.\[peers\]'"
        ):
            load_engine(name)
    engine = _engine(name)
    with pytest.raises(ConfigError, match=f"{name}: friction = 5.0 is not in"):
        engine.simulate(_tosses([_state([0, 0, 1], [1, 0, 0, 0], [0] * 3, [0] * 3)], [2]),
                        nominal(engine.PARAMETERS) | {"friction": 5.0}, TABLE)  # fmt: skip

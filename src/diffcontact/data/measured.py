"""Import measured tosses as a dataset that ``train`` and ``evaluate`` read like a generated one.

From recorded poses (``data/tosses.py``) to the 4-point states of the box task (``systems/poses.py``):

- **table at z = 0**: the table's height is estimated from the resting frames (the median lowest corner over each
  toss's last 5 frames) and subtracted from every z; it is recorded, and predictions are moved back.
- **velocities from the poses**: central differences of positions, (p_{k+1} − p_{k−1}) / 2dt, and of rotations,
  log(R_{k−1}ᵀ R_{k+1}) / 2dt (body frame); one-sided of second order at a toss's ends. The sources' velocity
  columns are backward differences, median-filtered: in free flight they lag a local quadratic fit of the positions
  by 0.032 m/s (median over 4,099 frames of the ContactNets tosses), the central differences by 0.0027 m/s.
- **contact flags**: a frame is in contact where the lowest corner is within ``CONTACT_HEIGHT`` of the table.
- **splits by toss** (seeded): the training and validation tosses are cut into windows of ``window`` frames
  (``stride`` apart) that are the split's trajectories and chunks; the test split holds whole tosses, padded to
  the longest by repeating the last frame; ``tosses.npz`` keeps every toss's recorded poses (source frame, SI).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import torch

from diffcontact.config import load_task
from diffcontact.data.store import FORMAT, SPLITS, config_json, describe, remove_stale, save_meta
from diffcontact.data.tosses import (
    SAMPLE,
    Tosses,
    read_tosses,
    resting_table_height,
    split_tosses,
    training_subset,
)
from diffcontact.errors import DatasetError
from diffcontact.files import check_output, save_arrays, sha256, versions
from diffcontact.systems.poses import (
    box_vertices,
    matrix_to_quaternion,
    pose_to_points,
    quaternion_to_matrix,
    rotate,
    rotation_vector,
)

CONTACT_HEIGHT = 0.003  # m: a frame whose lowest corner is this close to the table is flagged as in contact
# A toss's first state (``first_states``): fitted to up to FLIGHT_FRAMES frames of free flight (the lowest corner
# above FLIGHT_CLEARANCE), if it starts with at least MIN_FLIGHT_FRAMES of them.  15 frames (0.1 s) measured best of
# 4, 6, 10, 15, 25 and 40 on the validation tosses with the nominal model (docs/real_data.md).
FLIGHT_FRAMES, MIN_FLIGHT_FRAMES, FLIGHT_CLEARANCE = 15, 3, 0.005
GRAVITY = 9.81  # m/s²
TOSSES_FILE = "tosses.npz"


def finite_difference_twist(tosses: Tosses) -> tuple[np.ndarray, np.ndarray]:
    """Velocities (F, 3) m/s and body-frame angular velocities (F, 3) rad/s of every frame from the poses: central
    differences inside a toss, (p_{k+1} − p_{k−1}) / 2dt and log(R_{k−1}ᵀ R_{k+1}) / 2dt; at its first and last
    frame the one-sided second-order ones, (−3 p_0 + 4 p_1 − p_2) / 2dt and (4 log(R_0ᵀ R_1) − log(R_0ᵀ R_2)) / 2dt
    (mirrored at the end): all exact for a parabola and a steady spin. Tosses need 3 frames."""
    dt = tosses.dt
    R = quaternion_to_matrix(torch.from_numpy(tosses.quaternion))
    p = tosses.position

    def turn(i, j):  # (the rotation vectors of R_iᵀ R_j, in the body frame of i)
        return rotation_vector(matrix_to_quaternion(R[i].mT @ R[j])).numpy()

    rows = np.arange(len(p))
    first, last = np.isin(rows, tosses.offsets[:-1]), np.isin(rows, tosses.offsets[1:] - 1)
    inner = ~(first | last)
    velocity, omega = np.empty_like(p), np.empty_like(p)
    k = rows[inner]
    velocity[k] = (p[k + 1] - p[k - 1]) / (2 * dt)
    omega[k] = turn(k - 1, k + 1) / (2 * dt)
    k = rows[first]
    velocity[k] = (-3 * p[k] + 4 * p[k + 1] - p[k + 2]) / (2 * dt)
    omega[k] = (4 * turn(k, k + 1) - turn(k, k + 2)) / (2 * dt)
    k = rows[last]
    velocity[k] = (3 * p[k] - 4 * p[k - 1] + p[k - 2]) / (2 * dt)
    omega[k] = (-4 * turn(k, k - 1) + turn(k, k - 2)) / (2 * dt)
    return velocity, omega


def first_state_settings() -> dict:
    """The settings of ``first_states``, as a dataset records them."""
    return {
        "flight_frames": FLIGHT_FRAMES,
        "min_flight_frames": MIN_FLIGHT_FRAMES,
        "flight_clearance_m": FLIGHT_CLEARANCE,
        "gravity_m_s2": GRAVITY,
    }


def lowest_corner(tosses: Tosses, table_height: float, half_extents) -> np.ndarray:
    """(F,) height in m of every frame's lowest corner above the table."""
    corners = rotate(tosses.quaternion, box_vertices(half_extents))[..., 2]
    return (tosses.position[:, None, 2] - table_height + corners).min(1)


def flight_frames(tosses: Tosses, table_height: float, half_extents) -> list[int]:
    """The frames each toss's first state is fitted to: its first frames of free flight (the lowest corner above
    ``FLIGHT_CLEARANCE``), at most ``FLIGHT_FRAMES``."""
    airborne = lowest_corner(tosses, table_height, half_extents) > FLIGHT_CLEARANCE
    frames = []
    for i in range(len(tosses.lengths)):
        grounded = np.flatnonzero(~airborne[tosses.frames_of(i)])
        frames.append(min(FLIGHT_FRAMES, int(grounded[0]) if len(grounded) else int(tosses.lengths[i])))
    return frames


def first_states(tosses: Tosses, table_height: float, half_extents) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The state each toss is rolled out from: position (n, 3) m, velocity (n, 3) m/s and body-frame angular
    velocity (n, 3) rad/s at its first frame (its recorded quaternion is kept).

    Where a toss starts in free flight (lowest corner above ``FLIGHT_CLEARANCE``) for at least
    ``MIN_FLIGHT_FRAMES`` frames, they are the least-squares fit of a free flight to its first ``FLIGHT_FRAMES``
    of them: p_k = p_0 + v_0 t_k − ½ g t_k² e_z (g = ``GRAVITY``) and log(R_0ᵀ R_k) = ω t_k (a torque-free spin,
    steady for the cube's isotropic inertia); elsewhere the first frame of ``finite_difference_twist`` and the
    recorded position.  A pose's noise enters a three-frame difference about 20 times amplified at 148 Hz; the fit
    averages it out (measured on validation tosses in docs/real_data.md)."""
    velocity, omega = finite_difference_twist(tosses)
    first = tosses.offsets[:-1]
    position, velocity, omega = tosses.position[first].copy(), velocity[first], omega[first]
    R = quaternion_to_matrix(torch.from_numpy(tosses.quaternion))
    for i, (start, m) in enumerate(zip(first.tolist(), flight_frames(tosses, table_height, half_extents), strict=True)):
        if m < MIN_FLIGHT_FRAMES:
            continue
        t = np.arange(m) * tosses.dt
        lifted = tosses.position[start : start + m] + np.outer(0.5 * GRAVITY * t**2, [0.0, 0.0, 1.0])
        (position[i], velocity[i]), *_ = np.linalg.lstsq(np.stack([np.ones(m), t], 1), lifted, rcond=None)
        turns = rotation_vector(matrix_to_quaternion(R[start].mT @ R[start : start + m])).numpy()
        omega[i] = t @ turns / (t @ t)
    return position, velocity, omega


def with_first_states(tosses: Tosses, table_height: float, half_extents) -> Tosses:
    """``tosses`` with each toss's first position, velocity and angular velocity replaced by ``first_states``: the
    state a rollout of it starts from, for our models and the peers alike."""
    first = tosses.offsets[:-1]
    arrays = {k: getattr(tosses, k).copy() for k in ("position", "velocity", "omega")}
    arrays["position"][first], arrays["velocity"][first], arrays["omega"][first] = first_states(
        tosses, table_height, half_extents
    )
    return dataclasses.replace(tosses, **arrays)


def tosses_to_points(tosses: Tosses, table_height: float, half_extents) -> tuple[np.ndarray, np.ndarray]:
    """The 4-point states x, v (F, 4, 3) of every recorded frame, with the table moved to z = 0 and the velocities
    from the poses: each toss's first frame from ``first_states``, the others from ``finite_difference_twist``."""
    velocity, omega = finite_difference_twist(tosses)
    tosses = with_first_states(dataclasses.replace(tosses, velocity=velocity, omega=omega), table_height, half_extents)
    position = tosses.position - np.array([0.0, 0.0, table_height])
    arrays = (position, tosses.quaternion, tosses.velocity, tosses.omega)
    x, v = pose_to_points(*(torch.from_numpy(a) for a in arrays))
    return x.numpy(), v.numpy()


def _windows(starts_of: list[np.ndarray], offsets: np.ndarray, window: int) -> np.ndarray:
    """Frame indices (N_w, window) of the windows starting at ``starts_of[i]`` (relative) in each toss i."""
    rows = [offsets[i] + s[:, None] + np.arange(window)[None] for i, s in enumerate(starts_of)]
    return np.concatenate(rows) if rows else np.zeros((0, window), dtype=np.int64)


def _split_arrays(x, v, contact, frame_rows: np.ndarray, lengths: np.ndarray | None, dt: float) -> dict:
    """A split's arrays in the stored layout (``data/store.py``) from frame indices (N, T) into the states."""
    T = frame_rows.shape[1]
    xs, vs = x[frame_rows], v[frame_rows]
    hit = contact[frame_rows]
    if lengths is not None:  # (padded frames repeat the last recorded one: no contact flag there)
        hit = hit & (np.arange(T)[None] < lengths[:, None])
    return {
        "x": xs,
        "v": vs,
        "contact": hit,
        "t": np.arange(T) * dt,
        "chunk_start": np.zeros(len(xs), dtype=np.int64),
        "chunk_x": xs,
        "chunk_v": vs,
        "chunk_collision": hit.any(1),
    }


def import_tosses(
    source: str | Path,
    out: str | Path,
    *,
    task: str = "CubeToss",
    split: tuple[float, float, float] = (0.8, 0.1, 0.1),
    seed: int = 0,
    all_test: bool = False,
    window: int = 80,
    stride: int = 80,
    train_tosses: int | None = None,
    echo=None,
) -> dict:
    """Import a ContactNets source (a folder of ``K.pt`` files or a tosses ``.npz``) into the dataset folder ``out``
    for ``task`` (a box task); returns its metadata. ``split``: fractions (train, val, test) of the tosses, drawn
    by toss from ``seed``; ``all_test``: every toss in the test split (no training data). Training and validation
    tosses are cut into windows of ``window`` frames, ``stride`` apart; ``train_tosses`` N: only N of the training
    tosses (``training_subset``: seeded, nested; the validation and test tosses are the same for every N).
    DatasetError, with nothing written, for bad input: a file in neither layout, a non-finite value, a quaternion
    not of unit norm, a toss shorter than the window, an empty split."""
    started = time.perf_counter()
    cfg = load_task(task)
    if cfg.system != "box":
        raise DatasetError(f"task {cfg.name!r} is a {cfg.system!r} system; measured tosses need a box task")
    if window < 2 or stride < 1:
        raise DatasetError(f"window = {window} must be >= 2 and stride = {stride} >= 1")
    if len(split) != 3 or any(not (f >= 0) for f in split) or abs(sum(split) - 1.0) > 1e-9:
        raise DatasetError(f"split = {list(split)} must be three fractions >= 0 (train, val, test) that sum to 1")
    tosses = read_tosses(source)
    source_path = SAMPLE if str(source) == "sample" else Path(source)
    short = np.nonzero(tosses.lengths < window)[0]
    if len(short):
        i = int(short[0])
        raise DatasetError(
            f"{source}: toss {int(tosses.toss_id[i])} has {int(tosses.lengths[i])} frames, shorter than the window "
            f"({window} frames); every toss must have at least {window}"
        )
    body = cfg.section("body")
    half = body.numbers("half_extents", length=3)
    parts = (
        {"train": np.zeros(0, np.int64), "val": np.zeros(0, np.int64), "test": np.arange(tosses.n)}
        if all_test
        else split_tosses(tosses.n, split, seed)
    )
    if not all_test:
        parts["train"] = training_subset(parts["train"], train_tosses, seed)
    for name in ("train", "val") if not all_test else ():
        if len(parts[name]) == 0:
            raise DatasetError(f"{source}: split {name} is empty ({tosses.n} tosses at {list(split)})")
    if len(parts["test"]) == 0:
        raise DatasetError(f"{source}: split test is empty ({tosses.n} tosses at {list(split)})")
    # (from the training and validation tosses: the test tosses stay unseen; with --all-test, from all)
    seen = np.arange(tosses.n) if all_test else np.sort(np.concatenate([parts["train"], parts["val"]]))
    height, spread = resting_table_height(tosses.subset(seen), half)

    out = check_output(out, "--out", folder=True)
    x, v = tosses_to_points(tosses, height, half)
    contact = lowest_corner(tosses, height, half) <= CONTACT_HEIGHT

    arrays: dict[str, dict] = {}
    for name in ("train", "val"):
        if len(parts[name]):
            starts = [np.arange(0, int(tosses.lengths[i]) - window + 1, stride) for i in parts[name]]
            rows = _windows(starts, tosses.offsets[parts[name]], window)
            arrays[name] = _split_arrays(x, v, contact, rows, None, tosses.dt)
    test = parts["test"]
    T = int(tosses.lengths[test].max())
    rows = np.minimum(tosses.offsets[test][:, None] + np.arange(T)[None], tosses.offsets[test + 1][:, None] - 1)
    arrays["test"] = _split_arrays(x, v, contact, rows, tosses.lengths[test], tosses.dt)

    remove_stale(out)
    out.mkdir(parents=True, exist_ok=True)
    kept = tosses.subset(np.sort(np.concatenate([parts[k] for k in SPLITS])))
    tosses_sha = save_arrays(out / TOSSES_FILE, kept.arrays())
    meta = {
        "format": FORMAT,
        "request": {
            "task": cfg.name,
            "config": config_json(cfg),
            "dt": tosses.dt,
            "frames": window,
            "measured": True,
            "source": {"path": str(source_path.resolve()), "sha256": _source_digest(source_path)},
            "units": {"length": "m", "time": "s", "angle": "rad", "source_length_scale_m": _scale_note(source_path)},
            "split": list(split),
            "seed": seed,
            "all_test": all_test,
            "train_tosses": len(parts["train"]),
            "train_tosses_requested": train_tosses,
            "window": window,
            "stride": stride,
            "toss_ids": {k: tosses.toss_id[parts[k]].tolist() for k in SPLITS},
            "table_height_m": height,
            "table_height_iqr_m": spread,
            "table_height_method": "median over the training and validation tosses (all with all_test) of the lowest "
            "corner's z over each toss's last 5 frames",
            "velocity_method": "central differences of the recorded poses (one-sided, second order, at a toss's "
            "last frame); at a toss's first frame, the free-flight fit of first_states",
            "first_state": first_state_settings(),
            "contact_flag": f"lowest corner within {CONTACT_HEIGHT} m of the table",
            "half_extents_m": half,
            "tosses_file": {"file": TOSSES_FILE, "sha256": tosses_sha},
        },
        "versions": versions(),
        "splits": {},
    }
    for name, arr in arrays.items():
        digest = save_arrays(out / f"{name}.npz", arr)
        meta["splits"][name] = {
            "file": f"{name}.npz",
            "sha256": digest,
            "n": int(len(arr["x"])),
            "tosses": int(len(parts[name])),
            "arrays": describe(arr),
            "chunks_with_collision": int(arr["chunk_collision"].sum()),
            "collision_frames": int(arr["contact"].sum()),
        }
        if name == "test":
            meta["splits"][name]["lengths"] = tosses.lengths[test].tolist()
    meta["seconds"] = round(time.perf_counter() - started, 3)
    save_meta(out, meta)  # (last: its presence marks a complete dataset)
    if echo:
        sizes = ", ".join(f"{k} {len(parts[k])} tosses ({meta['splits'][k]['n']} rows)" for k in meta["splits"])
        echo(f"{cfg.name}: {tosses.n} tosses from {source} -> {out}: {sizes}; table at {height * 1000:.2f} mm")
    return meta


def _source_digest(path: Path) -> str:
    """SHA-256 of a source file, or of the sorted (name, SHA-256) list of a folder's ``.pt`` files."""
    if path.is_file():
        return sha256(path)
    import hashlib

    digest = hashlib.sha256()
    for p in sorted(path.glob("*.pt"), key=lambda p: p.name):
        digest.update(f"{p.name} {sha256(p)}\n".encode())
    return digest.hexdigest()


def _scale_note(source: str | Path) -> float:
    path = Path(source)
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            if "length_scale_m" in z:
                return float(z["length_scale_m"])
    from diffcontact.data.tosses import CONTACTNETS_LENGTH_SCALE

    return CONTACTNETS_LENGTH_SCALE

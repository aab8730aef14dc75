"""Measured tosses of a rigid body: recorded poses and twists, of varying lengths, in SI units.

The source formats are those of the ContactNets cube tosses (Pfrommer, Halm, Posa, CoRL 2020):

- a folder of ``K.pt`` files (DAIRLab/contact-nets ``data/tosses_processed``), each a float64 tensor (1, T, 19);
- one ``.npz`` with ``frames`` (F, 13), ``offsets`` (n + 1,), ``toss_id`` (n,) and ``length_scale_m``.

Columns 0–12 of either: centre x y z (table frame, z up, in units of ``length_scale``), quaternion w x y z (body to
table), centre velocity (table frame, length units/s; finite differences, median-filtered), angular velocity in the
body frame (rad/s). Columns 13–18 of a ``.pt`` (a control input) must be zero. Frames are ``dt`` apart (1/148 s).
"""

from __future__ import annotations

import re
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diffcontact.errors import DatasetError

CONTACTNETS_DT = 1.0 / 148.0  # s between frames
CONTACTNETS_LENGTH_SCALE = 0.0524  # m: the cube's half-width, the unit of the source's positions
UNIT_NORM_TOL = 1e-6  # |‖q‖ − 1| allowed of a recorded quaternion
#: 20 real tosses shipped with the package (BSD-3, samples/LICENSE-contactnets.txt): ``read_tosses("sample")``
SAMPLE = Path(__file__).resolve().parent / "samples" / "contactnets_cube_20.npz"


@dataclass(frozen=True)
class Tosses:
    """Tosses as flat frame arrays: toss i is frames ``offsets[i]:offsets[i + 1]``.

    position (F, 3) m and velocity (F, 3) m/s of the centre in the table frame; quaternion (F, 4) w, x, y, z, body
    to table; omega (F, 3) rad/s in the body frame; offsets (n + 1,) int64; toss_id (n,) int64 (the source's file
    number); dt in s."""

    position: np.ndarray
    quaternion: np.ndarray
    velocity: np.ndarray
    omega: np.ndarray
    offsets: np.ndarray
    toss_id: np.ndarray
    dt: float

    @property
    def n(self) -> int:
        return int(len(self.toss_id))

    @property
    def lengths(self) -> np.ndarray:
        return np.diff(self.offsets)

    def frames_of(self, i: int) -> slice:
        return slice(int(self.offsets[i]), int(self.offsets[i + 1]))

    def subset(self, index: np.ndarray) -> Tosses:
        """The tosses ``index`` (m,) (positions into this set), in that order."""
        index = np.asarray(index, dtype=np.int64)
        rows = (
            np.concatenate([np.arange(int(self.offsets[i]), int(self.offsets[i + 1])) for i in index])
            if len(index)
            else []
        )
        rows = np.asarray(rows, dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(self.lengths[index])]).astype(np.int64)
        pick = {k: getattr(self, k)[rows] for k in ("position", "quaternion", "velocity", "omega")}
        return Tosses(**pick, offsets=offsets, toss_id=self.toss_id[index], dt=self.dt)

    def arrays(self) -> dict[str, np.ndarray | np.float64]:
        """The arrays to store (``save_arrays``), dt included."""
        keys = ("position", "quaternion", "velocity", "omega", "offsets", "toss_id")
        return {k: getattr(self, k) for k in keys} | {"dt": np.float64(self.dt)}


def _from_frames(
    frames: np.ndarray, offsets: np.ndarray, toss_id: np.ndarray, scale: float, dt: float, where: str
) -> Tosses:
    """Tosses in SI from source frames (F, 13) in length units; DatasetError naming ``where`` and the toss."""
    for i in range(len(toss_id)):
        f = frames[offsets[i] : offsets[i + 1]]
        name = f"{where}, toss {int(toss_id[i])}"
        if not np.isfinite(f).all():
            row, col = (int(a[0]) for a in np.nonzero(~np.isfinite(f)))
            raise DatasetError(f"{name}: frame {row}, column {col} is not finite (every value must be finite)")
        norm = np.linalg.norm(f[:, 3:7], axis=1)
        bad = np.abs(norm - 1.0) > UNIT_NORM_TOL
        if bad.any():
            row = int(np.argmax(bad))
            raise DatasetError(
                f"{name}: frame {row} has a quaternion of norm {norm[row]:.9g} (columns 3-6 must be a unit "
                f"quaternion, |norm - 1| <= {UNIT_NORM_TOL:g})"
            )
    return Tosses(
        position=frames[:, 0:3] * scale,
        quaternion=frames[:, 3:7] / np.linalg.norm(frames[:, 3:7], axis=1, keepdims=True),
        velocity=frames[:, 7:10] * scale,
        omega=frames[:, 10:13].copy(),
        offsets=offsets.astype(np.int64),
        toss_id=toss_id.astype(np.int64),
        dt=dt,
    )


def _read_npz(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in ("frames", "offsets", "toss_id") if k not in z]
            if missing:
                raise DatasetError(
                    f"{path}: lacks arrays {missing}; a tosses .npz holds frames (F, 13), offsets (n + 1,), "
                    "toss_id (n,) and length_scale_m (the ContactNets layout)"
                )
            frames, offsets, toss_id = z["frames"], z["offsets"], z["toss_id"]
            scale = float(z["length_scale_m"]) if "length_scale_m" in z else CONTACTNETS_LENGTH_SCALE
            dt = float(z["dt"]) if "dt" in z else CONTACTNETS_DT
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise DatasetError(f"{path} is not a readable .npz: {err}") from err
    if frames.ndim != 2 or frames.shape[1] != 13 or not np.issubdtype(frames.dtype, np.floating):
        raise DatasetError(f"{path}: frames is {frames.dtype}{list(frames.shape)}, expected float (F, 13)")
    n = len(toss_id)
    if offsets.shape != (n + 1,) or offsets[0] != 0 or offsets[-1] != len(frames) or (np.diff(offsets) <= 0).any():
        raise DatasetError(
            f"{path}: offsets must be {n + 1} increasing values from 0 to {len(frames)} (one toss per toss_id)"
        )
    if not (np.isfinite(scale) and scale > 0 and np.isfinite(dt) and dt > 0):
        raise DatasetError(f"{path}: length_scale_m = {scale} and dt = {dt} must be finite and > 0")
    return frames.astype(np.float64), offsets.astype(np.int64), toss_id.astype(np.int64), scale, dt


def _read_pt_folder(folder: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    import torch

    files = sorted((p for p in folder.iterdir() if re.fullmatch(r"\d+\.pt", p.name)), key=lambda p: int(p.stem))
    if not files:
        raise DatasetError(f"{folder}: no K.pt files (a ContactNets tosses_processed folder holds 0.pt, 1.pt, ...)")
    frames, ids = [], []
    for path in files:
        try:
            t = torch.load(path, weights_only=True, map_location="cpu")
        except Exception as err:  # (torch raises many kinds on a corrupt file)
            raise DatasetError(f"{path} is not a readable torch tensor file: {err}") from err
        if not isinstance(t, torch.Tensor) or t.ndim != 3 or t.shape[0] != 1 or t.shape[2] != 19:
            shape = list(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
            raise DatasetError(f"{path}: holds {shape}, expected a tensor (1, T, 19) (ContactNets layout)")
        a = t[0].double().numpy()
        if np.isfinite(a[:, 13:]).all() and (a[:, 13:] != 0).any():
            raise DatasetError(f"{path}: columns 13-18 (the control input) must be zero for a free toss")
        frames.append(a[:, :13])
        ids.append(int(path.stem))
    offsets = np.concatenate([[0], np.cumsum([len(f) for f in frames])])
    return np.concatenate(frames), offsets, np.array(ids), CONTACTNETS_LENGTH_SCALE, CONTACTNETS_DT


def read_tosses(source: str | Path) -> Tosses:
    """Tosses in SI units from a ContactNets source: a folder of ``K.pt`` files or an ``.npz`` (module docstring);
    "sample": the 20 tosses shipped with the package (:data:`SAMPLE`).

    Raises DatasetError, naming the file and the toss, for a file in neither layout, a non-finite value or a
    quaternion that is not of unit norm."""
    path = SAMPLE if str(source) == "sample" else Path(source)
    if path.is_dir():
        frames, offsets, ids, scale, dt = _read_pt_folder(path)
    elif path.is_file():
        frames, offsets, ids, scale, dt = _read_npz(path)
    else:
        raise DatasetError(f"{path} does not exist (give a folder of ContactNets K.pt files or a tosses .npz)")
    return _from_frames(frames, offsets, ids, scale, dt, str(path))


def load_tosses(path: str | Path) -> Tosses:
    """Tosses stored by ``save_arrays(path, tosses.arrays())``."""
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = ("position", "quaternion", "velocity", "omega", "offsets", "toss_id")
            return Tosses(**{k: z[k] for k in keys}, dt=float(z["dt"]))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as err:
        raise DatasetError(f"{path} is corrupt or incomplete: {err}") from err


def resting_table_height(tosses: Tosses, half_extents, frames: int = 5) -> tuple[float, float]:
    """The table plane's height estimated from resting frames: the median over tosses of the lowest corner's z (m)
    over each toss's last ``frames`` frames (every toss ends at rest), and the interquartile range of those (m)."""
    from diffcontact.systems.poses import box_vertices, rotate

    corners = box_vertices(half_extents)
    lows = []
    for i in range(tosses.n):
        end = int(tosses.offsets[i + 1])
        rows = slice(max(end - frames, int(tosses.offsets[i])), end)
        z = tosses.position[rows, None, 2] + rotate(tosses.quaternion[rows], corners)[..., 2]
        lows.append(z.min(1).mean())
    q1, med, q3 = np.percentile(lows, [25, 50, 75])
    return float(med), float(q3 - q1)


def split_tosses(n: int, fractions: tuple[float, float, float], seed: int) -> dict[str, np.ndarray]:
    """A seeded split of n tosses by toss into train / val / test (positions into the set, sorted): the counts are
    round(fraction · n) for val and test, the rest train. DatasetError for a split that would be empty."""
    rng = np.random.default_rng(seed)
    order = rng.permutation(n)
    n_val, n_test = round(fractions[1] * n), round(fractions[2] * n)
    n_train = n - n_val - n_test
    parts = {"train": order[:n_train], "val": order[n_train : n_train + n_val], "test": order[n_train + n_val :]}
    for name, part in parts.items():
        if len(part) == 0 and fractions[("train", "val", "test").index(name)] > 0:
            raise DatasetError(f"split {name} of {n} tosses at fraction {fractions} is empty (give more tosses)")
    return {k: np.sort(v) for k, v in parts.items()}


def training_subset(train: np.ndarray, n: int | None, seed: int) -> np.ndarray:
    """The first ``n`` of the training tosses ``train`` (positions) in an order drawn from ``seed`` (all if None):
    the tosses of a training-size sweep, the same for every method, nested (a smaller N's are in every larger N's)."""
    if n is None:
        return train
    if not 1 <= n <= len(train):
        raise DatasetError(f"train_tosses = {n} is not in [1, {len(train)}] (the tosses of the training split)")
    return np.sort(np.random.default_rng([seed, 1]).permutation(train)[:n])


def simulated_tosses(
    task, n: int, seed: int, frames: int, position_noise: float = 2e-5, rotation_noise: float = 3e-4
) -> Tosses:
    """``n`` tosses of a box task simulated with its own Params (CM, float64), as a measurement system records them:
    poses with Gaussian noise (``position_noise`` m per axis; a rotation of ``rotation_noise`` rad per axis), and
    the sources' velocity columns (backward differences, then a 3-frame median filter). The default noise is the
    ContactNets tosses' own: residuals of a local quadratic fit in free flight, 0.016-0.020 mm and 0.016°."""
    import torch

    from diffcontact.simulator import simulator_for
    from diffcontact.systems.poses import matrix_to_quaternion, points_to_pose, quaternion_to_matrix

    sim = simulator_for(task)
    with torch.no_grad():
        xs, vs, _ = sim.rollout(task.sample(n, seed), task.params, task.dt, frames)
    position, quaternion, _, _ = points_to_pose(xs.double(), vs.double())  # (n, T, 3), (n, T, 4)
    gen = torch.Generator().manual_seed(seed + 1)
    position = position + position_noise * torch.randn(position.shape, generator=gen, dtype=torch.float64)
    turn = rotation_noise * torch.randn(position.shape, generator=gen, dtype=torch.float64)
    angle = turn.norm(dim=-1, keepdim=True)
    half = torch.cat([torch.cos(angle / 2), torch.sinc(angle / (2 * torch.pi)) * turn / 2], -1)  # exp of turn
    R = quaternion_to_matrix(quaternion) @ quaternion_to_matrix(half)
    quaternion = matrix_to_quaternion(R)
    p, q = position.reshape(-1, 3).numpy(), quaternion.reshape(-1, 4).numpy()
    offsets = np.arange(n + 1, dtype=np.int64) * frames
    tosses = Tosses(p, q, 0 * p, 0 * p, offsets, np.arange(n, dtype=np.int64), task.dt)
    return _recorded_velocities(tosses)


def _recorded_velocities(tosses: Tosses) -> Tosses:
    """The tosses with the sources' velocity columns: backward differences of the poses, p_k − p_{k−1} over dt and
    the rotation vector of R_{k−1}ᵀ R_k over dt (the first frame repeats the second's), then a 3-frame median
    filter per component."""
    import torch

    from diffcontact.systems.poses import matrix_to_quaternion, quaternion_to_matrix, rotation_vector

    R = quaternion_to_matrix(torch.from_numpy(tosses.quaternion))
    rows = np.arange(len(tosses.position))
    starts = np.isin(rows, tosses.offsets[:-1])
    prev = np.where(starts, rows + 1, rows) - 1  # (k − 1; at a toss's first frame the pair of its second)
    cur = np.where(starts, rows + 1, rows)
    velocity = (tosses.position[cur] - tosses.position[prev]) / tosses.dt
    omega = rotation_vector(matrix_to_quaternion(R[prev].mT @ R[cur])).numpy() / tosses.dt
    ends = np.isin(rows, tosses.offsets[1:] - 1)
    before, after = np.where(starts, rows, rows - 1), np.where(ends, rows, rows + 1)

    def median3(a):
        return np.median(np.stack([a[before], a, a[after]]), axis=0)

    return Tosses(
        tosses.position, tosses.quaternion, median3(velocity), median3(omega), tosses.offsets, tosses.toss_id, tosses.dt
    )


def save_contactnets_npz(path: str | Path, tosses: Tosses, length_scale: float = CONTACTNETS_LENGTH_SCALE) -> str:
    """Write tosses in the ContactNets .npz layout (positions and velocities in units of ``length_scale``); returns
    the file's SHA-256."""
    from diffcontact.files import save_arrays

    frames = np.concatenate(
        [tosses.position / length_scale, tosses.quaternion, tosses.velocity / length_scale, tosses.omega], 1
    )
    arrays = {
        "frames": frames,
        "offsets": tosses.offsets,
        "toss_id": tosses.toss_id,
        "length_scale_m": np.float64(length_scale),
        "dt": np.float64(tosses.dt),
    }
    return save_arrays(path, arrays)

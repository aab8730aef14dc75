"""The field's metrics for a tossed box (ContactNets, Acosta et al.): predicted against recorded poses.

Every function takes one or many tosses as flat frame arrays with ``offsets`` (toss i is frames
``offsets[i]:offsets[i + 1]``), positions in m in the table frame (z up) and unit quaternions w, x, y, z (body to
table). Errors are averaged over the frames of each toss, then over tosses, so that a long toss counts once.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from diffcontact.systems.poses import box_vertices, rotate


def _check(name: str, a: np.ndarray, cols: int) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != cols:
        raise ValueError(f"{name} has shape {a.shape}, expected (frames, {cols})")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} is not finite from frame {int(np.argmin(np.isfinite(a).all(1)))}")
    return a


def per_toss_mean(values: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """The mean of ``values`` (frames,) over each toss: (n_tosses,)."""
    offsets = np.asarray(offsets, dtype=np.int64)
    if offsets[0] != 0 or offsets[-1] != len(values) or (np.diff(offsets) <= 0).any():
        raise ValueError(f"offsets must rise from 0 to {len(values)} (frames), got {offsets[0]} … {offsets[-1]}")
    sums = np.add.reduceat(values, offsets[:-1])
    return sums / np.diff(offsets)


def rotation_angle(q_hat: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotations (frames,) in rad: 2 acos |⟨q̂, q⟩| (q and −q are the same rotation); the
    quaternions are normalised first."""
    q_hat = q_hat / np.linalg.norm(q_hat, axis=1, keepdims=True)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    dot = np.clip(np.abs((q_hat * q).sum(1)), 0.0, 1.0)
    return 2.0 * np.arccos(dot)


def penetration(position: np.ndarray, quaternion: np.ndarray, half_extents, table_height: float) -> np.ndarray:
    """Depth (frames,) in m of the lowest corner below the table plane z = ``table_height`` (0 where none is below)."""
    corners = position[:, None] + rotate(quaternion, box_vertices(half_extents))
    return np.maximum(table_height - corners[..., 2].min(1), 0.0)


def box_toss_metrics(
    position_hat: np.ndarray,
    quaternion_hat: np.ndarray,
    position: np.ndarray,
    quaternion: np.ndarray,
    offsets: np.ndarray,
    half_extents,
    table_height: float,
) -> dict[str, Any]:
    """The three numbers of a box-toss evaluation, each a mean over tosses of the mean over a toss's frames:

    - ``position_error_pct``: ‖p̂ − p‖ of the centre, in % of the box's width (2 half-extents along x);
    - ``rotation_error_deg``: the geodesic angle between predicted and recorded rotations, in degrees;
    - ``penetration_pct``: the depth of the predicted box's lowest corner below the table, in % of the width.

    Also where the error comes from: ``same_final_face``, the number of tosses whose last predicted frame has the
    recorded one's face down (``face_down``), and ``position_error_pct`` over those tosses and over the others
    (``position_error_pct_same_face``, ``position_error_pct_other_face``; None where there is none).

    position_hat, position: (frames, 3) m; quaternion_hat, quaternion: (frames, 4) w, x, y, z; offsets
    (n_tosses + 1,); half_extents (3,) m; table_height: the table plane's z in m.
    """
    position_hat, position = _check("position_hat", position_hat, 3), _check("position", position, 3)
    quaternion_hat, quaternion = _check("quaternion_hat", quaternion_hat, 4), _check("quaternion", quaternion, 4)
    if len(position_hat) != len(position) or len(quaternion_hat) != len(position) or len(quaternion) != len(position):
        raise ValueError("predicted and recorded arrays must have one row per recorded frame")
    width = 2.0 * float(np.asarray(half_extents, dtype=np.float64)[0])
    rot = np.degrees(rotation_angle(quaternion_hat, quaternion))
    pen = penetration(position_hat, quaternion_hat, half_extents, table_height) / width * 100.0
    per_toss = per_toss_position_error(position_hat, position, offsets, half_extents)
    last = np.asarray(offsets[1:]) - 1
    same = face_down(quaternion_hat[last]) == face_down(quaternion[last])
    return {
        "position_error_pct": float(per_toss.mean()),
        "rotation_error_deg": float(per_toss_mean(rot, offsets).mean()),
        "penetration_pct": float(per_toss_mean(pen, offsets).mean()),
        "tosses": int(len(offsets) - 1),
        "frames": int(len(position)),
        "same_final_face": int(same.sum()),
        "position_error_pct_same_face": float(per_toss[same].mean()) if same.any() else None,
        "position_error_pct_other_face": float(per_toss[~same].mean()) if not same.all() else None,
    }


#: The rotation error's weight in :func:`toss_objective`: the arc a face centre moves through per degree, in % of the
#: width (100 · h θ / 2h per rad).
ROTATION_WEIGHT = 50.0 * math.pi / 180.0
TOSS_OBJECTIVE = "position_error_pct + rotation_weight * rotation_error_deg"


def toss_objective(metrics: dict[str, Any]) -> float:
    """What a fit to whole tosses minimises, in % of the box's width: ``metrics``' (``box_toss_metrics``) position
    error plus ROTATION_WEIGHT times its rotation error: what the peers' fits minimise."""
    return float(metrics["position_error_pct"] + ROTATION_WEIGHT * metrics["rotation_error_deg"])


def per_toss_position_error(position_hat: np.ndarray, position: np.ndarray, offsets: np.ndarray, half_extents):
    """Each toss's mean position error of the centre, in % of the box's width: (n_tosses,).  position_hat, position
    (frames, 3) m; offsets (n_tosses + 1,); half_extents (3,) m."""
    width = 2.0 * float(np.asarray(half_extents, dtype=np.float64)[0])
    return per_toss_mean(np.linalg.norm(position_hat - position, axis=1) / width * 100.0, offsets)


def paired_difference(a: np.ndarray, b: np.ndarray, draws: int = 10_000, seed: int = 0) -> dict[str, float]:
    """The mean over tosses of a − b (two methods' errors on the same tosses, (n,)) and its 95 % interval by a
    seeded bootstrap over the tosses: {"mean", "lo", "hi", "tosses"}.  An interval that holds 0 does not separate
    the two methods on these tosses."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1 or not len(a):
        raise ValueError(f"paired errors must be two (n,) arrays of the same tosses, got {a.shape} and {b.shape}")
    d = a - b
    means = d[np.random.default_rng(seed).integers(0, len(d), size=(draws, len(d)))].mean(1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return {"mean": float(d.mean()), "lo": float(lo), "hi": float(hi), "tosses": int(len(d))}


def face_down(quaternion: np.ndarray) -> np.ndarray:
    """Which face of a box points down in each frame (frames, 4): 0 … 5 for the body's −x, +x, −y, +y, −z, +z face,
    the one whose outward normal is nearest to −z of the table."""
    normals_z = rotate(quaternion, np.eye(3))[..., 2]  # (frames, 3): the table-z of the body's +x, +y, +z axes
    axis = np.abs(normals_z).argmax(1)
    return 2 * axis + (normals_z[np.arange(len(axis)), axis] < 0)

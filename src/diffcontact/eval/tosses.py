"""Evaluate a model on measured tosses (``diffcontact import``) in the field's metrics (``eval/pose_metrics.py``).

Each test toss is rolled out over its whole length from its first recorded state; the predicted poses are moved
back to the source's table frame (the importer moved the table to z = 0) and scored against the recorded poses.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np
import torch
from torch import nn

from diffcontact.data.measured import tosses_to_points
from diffcontact.data.store import load_meta
from diffcontact.data.tosses import Tosses, load_tosses
from diffcontact.errors import DatasetError
from diffcontact.eval.pose_metrics import box_toss_metrics, paired_difference, per_toss_position_error
from diffcontact.eval.rollouts import predict
from diffcontact.files import save_arrays, versions, write_json
from diffcontact.run_dir import METRICS, PREDICTIONS
from diffcontact.systems.poses import points_to_pose

if TYPE_CHECKING:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from mpl_toolkits.mplot3d import Axes3D

SHOWN_TOSSES = 4  # test tosses drawn in the figure and the GIF


def measured(folder: str | Path) -> bool:
    """Whether the dataset in ``folder`` holds measured tosses (``diffcontact import``)."""
    return bool(load_meta(folder)["request"].get("measured"))


def recorded_tosses(folder: str | Path, split: str = "test") -> tuple[Tosses, dict]:
    """The recorded tosses of ``split`` (source frame, SI) and the request metadata of an imported dataset."""
    meta = load_meta(folder)
    request = meta["request"]
    if not request.get("measured"):
        raise DatasetError(f"{folder} holds simulated trajectories, not measured tosses")
    tosses = load_tosses(Path(folder) / request["tosses_file"]["file"])
    wanted = request["toss_ids"][split]
    if not wanted:
        raise DatasetError(f"{folder}: split {split} has no tosses")
    index = np.searchsorted(tosses.toss_id, wanted)
    return tosses.subset(index), request


def paired_position_errors(
    folder: str | Path,
    reference: str | Path | Sequence[str | Path],
    others: Mapping[str, str | Path],
    split: str = "test",
) -> dict[str, dict[str, float]]:
    """The per-toss position error of the predictions in ``reference`` (a predictions.npz of ``diffcontact
    evaluate`` or ``peers fit``; several: each toss's mean over them, such as a model's seeds) minus that of each of
    ``others`` on the same tosses of ``split``, as ``pose_metrics.paired_difference`` (mean and 95 % bootstrap
    interval, % of the width) by name."""
    tosses, request = recorded_tosses(folder, split)

    def errors(path: str | Path) -> np.ndarray:
        with np.load(path) as predicted:
            if not np.array_equal(predicted["toss_id"], tosses.toss_id):
                raise DatasetError(f"{path} holds predictions of other tosses than the {split} split of {folder}")
            position = predicted["position"]
        return per_toss_position_error(position, tosses.position, tosses.offsets, request["half_extents_m"])

    refs = [reference] if isinstance(reference, (str, Path)) else list(reference)
    base = np.mean([errors(path) for path in refs], axis=0)
    return {name: paired_difference(base, errors(path)) for name, path in others.items()}


def predict_tosses(net: nn.Module, folder: str | Path, split: str = "test") -> dict[str, Any]:
    """Roll ``net`` (x0, v0, frames) -> (x, v) out over every toss of ``split`` from its first recorded state (as the
    importer makes states: ``tosses_to_points``) and return the predicted poses in the source's frame: position
    (F, 3) m, quaternion (F, 4) w first, offsets, toss_id (one predicted frame per recorded frame), and ``diverged``
    {toss_id: first non-finite frame} of tosses whose prediction diverged, held at its last finite frame from there."""
    tosses, request = recorded_tosses(folder, split)
    x, v = tosses_to_points(tosses, request["table_height_m"], request["half_extents_m"])
    first = tosses.offsets[:-1]
    lengths = tosses.lengths
    x_hat, v_hat = predict(net, torch.from_numpy(x[first]), torch.from_numpy(v[first]), int(lengths.max()))
    keep = torch.from_numpy(np.arange(x_hat.shape[1])[None] < lengths[:, None])
    # a model that diverged (non-finite frames from some frame on) is held at its last finite frame there
    finite = (torch.isfinite(x_hat) & torch.isfinite(v_hat)).flatten(2).all(-1)  # (N, T)
    frame = torch.arange(x_hat.shape[1]).expand_as(finite)
    last_good = torch.where(finite, frame, 0).cummax(1).values
    held = ~finite & keep
    diverged = {int(tosses.toss_id[i]): int(held[i].nonzero()[0]) for i in held.any(1).nonzero().flatten().tolist()}
    x_hat = torch.gather(x_hat, 1, last_good[..., None, None].expand_as(x_hat))
    v_hat = torch.gather(v_hat, 1, last_good[..., None, None].expand_as(v_hat))
    position, quaternion, _, _ = points_to_pose(x_hat[keep].double(), v_hat[keep].double())
    position = position.numpy() + np.array([0.0, 0.0, request["table_height_m"]])
    return {
        "position": position,
        "quaternion": quaternion.numpy(),
        "offsets": tosses.offsets,
        "toss_id": tosses.toss_id,
        "diverged": diverged,
    }


def score_tosses(predicted: dict[str, np.ndarray], folder: str | Path, split: str = "test") -> dict:
    """The box-toss metrics of predictions (``predict_tosses``'s layout) against the recorded tosses of ``split``."""
    tosses, request = recorded_tosses(folder, split)
    if not np.array_equal(predicted["offsets"], tosses.offsets):
        raise ValueError("the predictions do not have one frame per recorded frame of every toss")
    return box_toss_metrics(
        predicted["position"],
        predicted["quaternion"],
        tosses.position,
        tosses.quaternion,
        tosses.offsets,
        request["half_extents_m"],
        request["table_height_m"],
    )


def evaluate_tosses(
    net: nn.Module,
    folder: str | Path,
    out: str | Path,
    split: str = "test",
    pictures: bool = True,
    on_solver_failure: Literal["raise", "count"] = "raise",
    **record,
) -> dict:
    """Predict and score every toss of ``split`` and write ``out``/metrics.json, predictions.npz, a figure of
    recorded against predicted trajectories (tosses.png) and, with ``pictures``, a 3-D GIF of a few tosses
    (tosses.gif); ``record``: entries added to metrics.json (the run, its config). ``on_solver_failure``: "raise"
    (a contact problem the solver fails on ends the evaluation) or "count" (its impulses are zero, and metrics.json
    counts the failures). Returns the metrics."""
    from diffcontact.models.model import ContactModelNet
    from diffcontact.solver import ContactSolver

    started = time.perf_counter()
    solver = ContactSolver(on_failure=on_solver_failure)
    if isinstance(net, ContactModelNet):
        sim = net.simulator
        sim.contact_model = dataclasses.replace(sim.contact_model, solver=solver)
    predicted = predict_tosses(net, folder, split)
    diverged = predicted.pop("diverged")
    metrics = score_tosses(predicted, folder, split)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_arrays(out / PREDICTIONS, predicted)
    tosses, request = recorded_tosses(folder, split)
    draw_tosses(tosses, predicted, out / "tosses.png", request["table_height_m"])
    if pictures:
        toss_gif(tosses, predicted, out / "tosses.gif", request["half_extents_m"], request["table_height_m"])
    metrics = {
        **metrics,
        "split": split,
        "data": str(folder),
        "table_height_m": request["table_height_m"],
        "diverged": {"tosses": len(diverged), "first_nonfinite_frame": diverged, "held": "at the last finite frame"},
        "solver": {"problems": solver.problems, "failures": solver.failures_by_status, "on_failure": on_solver_failure},
        "metric_definitions": {
            "position_error_pct": "mean over tosses of the mean over frames of |p_hat - p| / (2 half-extent) * 100",
            "rotation_error_deg": "the same mean of the geodesic angle 2 acos |<q_hat, q>| in degrees",
            "penetration_pct": "the same mean of the lowest predicted corner's depth below the table, % of width",
        },
        **record,
        "versions": versions(),
        "seconds": round(time.perf_counter() - started, 3),
    }
    write_json(out / METRICS, metrics)  # (last: its presence marks a finished evaluation)
    return metrics


def draw_tosses(tosses: Tosses, predicted: dict[str, np.ndarray], path: Path, table_height: float) -> Path:
    """Recorded (solid) against predicted (dashed) centre trajectories of the first ``SHOWN_TOSSES`` tosses: the
    path seen from above and the height over time."""
    from diffcontact.eval.plots import _pyplot
    from diffcontact.files import save_figure

    plt = _pyplot()
    fig, axes = plt.subplots(2, SHOWN_TOSSES, figsize=(3.2 * SHOWN_TOSSES, 6.0), squeeze=False)
    for i in range(min(SHOWN_TOSSES, tosses.n)):
        rows = tosses.frames_of(i)
        p, ph = tosses.position[rows], predicted["position"][rows]
        t = np.arange(len(p)) * tosses.dt
        top, side = axes[0, i], axes[1, i]
        top.plot(p[:, 0], p[:, 1], "k-", label="recorded")
        top.plot(ph[:, 0], ph[:, 1], "C3--", label="predicted")
        top.set_aspect("equal", adjustable="datalim")
        top.set_title(f"toss {int(tosses.toss_id[i])}", fontsize=9)
        top.set_xlabel("x (m)")
        side.plot(t, p[:, 2], "k-")
        side.plot(t, ph[:, 2], "C3--")
        side.axhline(table_height, color="0.6", lw=0.8)
        side.set_xlabel("t (s)")
    axes[0, 0].set_ylabel("y (m)")
    axes[1, 0].set_ylabel("centre height z (m)")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=90)
    plt.close(fig)
    return Path(path)


# the 12 edges of a box, as pairs of corner indices in box_vertices' order (x slowest): corners differing in one sign
_EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]


def toss_gif(
    tosses: Tosses, predicted: dict[str, np.ndarray], path: Path, half_extents, table_height: float, every: int = 3
) -> Path:
    """A GIF of the first ``SHOWN_TOSSES`` tosses side by side in 3-D: the recorded box (black) and the predicted one
    (red) every ``every`` frames, over the longest of them."""
    from diffcontact.eval.plots import _pyplot
    from diffcontact.files import save_gif
    from diffcontact.systems.poses import box_vertices, rotate

    plt = _pyplot()
    shown = min(SHOWN_TOSSES, tosses.n)
    corners = box_vertices(half_extents)
    boxes = []
    for i in range(shown):
        rows = tosses.frames_of(i)
        rec = tosses.position[rows, None] + rotate(tosses.quaternion[rows], corners)
        pre = predicted["position"][rows, None] + rotate(predicted["quaternion"][rows], corners)
        boxes.append((rec, pre))
    T = max(len(r) for r, _ in boxes)
    images = []
    for t in range(0, T, every):
        fig = plt.figure(figsize=(2.4 * shown, 2.6), dpi=70)
        for i, (rec, pre) in enumerate(boxes):
            ax = cast("Axes3D", fig.add_subplot(1, shown, i + 1, projection="3d"))
            k = min(t, len(rec) - 1)
            for box, color in ((rec[k], "k"), (pre[k], "tab:red")):
                for a, b in _EDGES:
                    ax.plot(*zip(box[a], box[b]), color=color, lw=1.2)
            lo, hi = np.minimum(rec.min((0, 1)), pre.min((0, 1))), np.maximum(rec.max((0, 1)), pre.max((0, 1)))
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[1], hi[1])
            ax.set_zlim(table_height, max(hi[2], table_height + 0.1))
            ax.set_title(f"toss {int(tosses.toss_id[i])}", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.zaxis.set_ticks([])
        fig.tight_layout()
        fig.canvas.draw()
        images.append(np.asarray(cast("FigureCanvasAgg", fig.canvas).buffer_rgba())[..., :3].copy())
        plt.close(fig)
    return save_gif(path, images, every * tosses.dt)

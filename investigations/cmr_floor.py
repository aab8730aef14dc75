"""The error floor of the regularised contact model (CMr) on the test trajectories (Fig. 4), with every property true.

    python investigations/cmr_floor.py CP3-e --runs runs/reproduction/runs
    python investigations/cmr_floor.py Gyro --runs runs/reproduction/runs

The simulator with CMr (effective mass A + reg·I) and the task's true inertia, potential, μ and e is rolled out in
float64 from the test trajectories' initial states and compared with the ground truth (CM, the same initial states):
the mean relative error per frame (Fig. 4's metric).  Scaling every mass and the potential by s leaves the smooth
dynamics unchanged and divides A by s, so a trained model whose learned inertia ended s times the true one
(``learned.json``: ``inertia.scale``) regularises like reg·s on the true scale: that row is the floor of the trained
CMr model, an error no training can remove.  With ``--runs`` the trained models' own Fig. 4 curves of the task
(``eval/metrics.json``) are printed beside it.  Writes nothing.
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
from pathlib import Path

import torch

SHOWN = (1, 2, 4, 8, 16, 32, 49)


def floor_curve(task_name: str, reg: float, data: str = "data", frames: int = 50) -> torch.Tensor:
    """Mean relative error per frame (frames,) of CMr with the true properties at ``reg`` (1/kg) against the truth."""
    from diffcontact.eval.metrics import error_curve, relative_error
    from diffcontact.eval.rollouts import ground_truth
    from diffcontact.simulator import simulator_for
    from diffcontact.state import State
    from diffcontact.systems import build_task

    task = build_task(task_name)
    x, v, _, dt = ground_truth(Path(data) / task_name, "test", frames)
    sim = simulator_for(task, reg=reg)
    params = task.params
    with torch.no_grad():
        xh, vh, _ = sim.rollout(State(x[:, 0].double(), v[:, 0].double()), params, dt, frames)
    return error_curve(relative_error(xh, vh, x.double(), v.double()), frames)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("task")
    ap.add_argument("--data", default="data")
    ap.add_argument("--regs", nargs="+", type=float, default=[0.0, 0.01], help="regularisations on the true scale")
    ap.add_argument("--runs", default=None, help="a reproduction's runs folder: add its trained models' curves")
    args = ap.parse_args()
    torch.set_num_threads(1)

    rows: list[tuple[str, list[float]]] = []
    trained: dict[str, list[float]] = {}
    regs = list(args.regs)
    if args.runs:
        for metrics in sorted(Path(args.runs, args.task).glob("*/seed0/eval/metrics.json")):
            model = metrics.parents[2].name
            trained[model] = json.loads(metrics.read_text())["error_curve"]
            learned = metrics.parents[1] / "learned.json"
            if model.startswith("CMr") and learned.exists():
                scale = json.loads(learned.read_text())["inertia"]["scale"]
                rows_reg = 0.01 * scale
                print(f"{model}: learned inertia {scale:.3f}× the true one: reg 0.01 acts as {rows_reg:.4g}")
                regs.append(rows_reg)
    for reg in regs:
        curve = floor_curve(args.task, reg, args.data)
        rows.append((f"CMr, true properties, reg {reg:.4g}" if reg else "CM, true properties", curve.tolist()))
    rows += [(f"trained {m}", c) for m, c in trained.items()]
    print(f"{args.task}: mean relative error at frame " + ", ".join(str(t) for t in SHOWN))
    print("| model | " + " | ".join(f"frame {t}" for t in SHOWN) + " |")
    print("|---|" + "---|" * len(SHOWN))
    for name, curve in rows:
        print(f"| {name} | " + " | ".join(f"{curve[t]:.2e}" for t in SHOWN) + " |")


if __name__ == "__main__":
    main()

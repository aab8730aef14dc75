"""A system of your own, end to end: three balls in a 3-D box (docs/custom_systems.md).

The system is declared in a task file: its bodies (masses, radii), the planes that bound it, gravity, and the
coefficients of its contact pairs (ball-ball and ball-plane).  The script writes that file, then simulates it,
generates a dataset and learns the masses, the potential, μ and e from the data with the library's functions,
which are exactly what ``diffcontact simulate | generate | train | evaluate ./box_of_balls.toml`` run.

    python examples/custom_system.py --out box_run           # a few minutes on 2 cores
    python examples/custom_system.py --out box_run --quick   # tiny data, 15 epochs: about 20 s of CPU
"""

from __future__ import annotations

import diffcontact as dc  # (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
from pathlib import Path

import torch

TASK_FILE = """\
[task]
name = "box-of-balls"
system = "bouncing"        # bodies that collide with each other and with planes (diffcontact.systems.bouncing)
dt = 0.01                  # s per frame
frames = 100
substeps = 1

[bodies]
kind = "point"             # balls: one point each, no rotation
dim = 3
masses = [0.1, 0.2, 0.3]   # kg
radii = [0.1, 0.12, 0.15]  # m

[walls]
# planes [a, b, c, d]: the side a x + b y + c z + d >= 0 is free; here the box [0, 1] x [0, 1] x [0, 1.5]
planes = [[1.0, 0.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 1.0],
          [0.0, 1.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.0],
          [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, -1.0, 1.5]]

[potential]
gravity = 9.81             # m/s², along -z

[contact]
# 21 contact pairs: the 3 ball-ball pairs (0,1), (0,2), (1,2), then ball b against plane w at 3 + 6 b + w.
# One value for all of them here (a list of 21 gives each pair its own).
mu = [0.2]
cor = [0.7]
time_of_impact = true      # impacts resolved at their time (exact gradients through collisions)

[init]
box = [[0.2, 0.8], [0.2, 0.8], [0.3, 1.2]]   # initial centres drawn uniformly here (m), out of contact
velocity_std = 1.0                           # m/s
"""


def main(out: Path, quick: bool) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    path = out / "box_of_balls.toml"
    path.write_text(TASK_FILE)

    task = dc.build_task(path)  # validated: a typo in a key is an error naming the key and the allowed ones
    print(f"{task.config.name}: {task.system.n_bodies} balls in {task.system.d}-D, {task.system.n_slots} contact pairs")
    state = task.sample(4, seed=0)  # diffcontact simulate ./box_of_balls.toml --n 4 --out x.npz
    with torch.no_grad():
        x, v, hit = dc.simulator_for(task).rollout(state, task.params, task.dt, task.frames)
    energy, impacts = task.system.energy(task.params, x[0], v[0]), int(hit[0].sum())
    print(f"simulated: energy {energy[0]:.3f} J -> {energy[-1]:.3f} J in {task.frames} frames, {impacts} impacts")

    sizes = dict(n_train=48, n_val=8, n_test=8) if quick else dict(n_train=400, n_val=50, n_test=50)
    dc.generate_dataset(path, out / "data", progress=False, **sizes)  # diffcontact generate ./box_of_balls.toml
    # diffcontact train ./box_of_balls.toml --data OUT/data --out OUT/run --epochs 15 --batch-size 8 --coef-lr 1
    # (μ and e at the full learning rate: the default preset's 1/6 is for 200 epochs)
    settings = dict(epochs=15, batch_size=8) if quick else dict(epochs=100, batch_size=16)
    summary = dc.train_run(str(path), data_root=out / "data", out=out / "run", coef_lr=1.0, progress=False, **settings)
    for key in ("mu", "e"):
        print(f"{key}: learned {summary[key]['learned'][0]:.4f}, true {summary[key]['true'][0]:.4f}")
    return summary


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("box_run"), help="Folder of the task file, data and run.")
    parser.add_argument("--quick", action="store_true", help="Tiny data and a few epochs.")
    args = parser.parse_args()
    main(args.out, args.quick)

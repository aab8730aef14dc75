"""The training loss as a function of μ and e around the truth, with every other property true (issue 13).

    python investigations/loss_landscape.py Gyro --out docs/figures/gyro_loss_landscape.png
    python investigations/loss_landscape.py Gyro --regs 0 1e-2 1e-3 1e-4 --no-grid      # the CMr bias in e

The loss is the training loss (mean absolute error of the predicted chunk, positions and velocities) over the
task's training chunks, predicted in float64 from each chunk's first frame by the exact simulator with the true
inertia and potential and (μ, e) set on every contact slot (homogeneous tasks only).  It answers two questions:
whether 5-frame chunks identify μ and e (one sharp minimum at the truth), and how far the regularised contact model
(CMr: the effective mass A + reg·I) moves the best e, and whether that bias vanishes as reg → 0.  Writes a JSON
beside the PNG with every value.
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch


def chunk_loss(sim, params, x: torch.Tensor, v: torch.Tensor, dt: float, batch: int = 800) -> float:
    """The training loss (0.5·(mean |x̂ − x| + mean |v̂ − v|)) of ``params`` on chunks x, v (N, L, P, d)."""
    from diffcontact.state import State

    total_x = total_v = 0.0
    with torch.no_grad():
        for i in range(0, len(x), batch):  # (memory only: each batch is one vectorised rollout)
            xb, vb = x[i : i + batch], v[i : i + batch]
            px, pv, _ = sim.rollout(State(xb[:, 0], vb[:, 0]), params, dt, xb.shape[1])
            total_x += float((px - xb).abs().sum())
            total_v += float((pv - vb).abs().sum())
    return 0.5 * (total_x + total_v) / x.numel()


def main() -> None:
    from diffcontact.data.store import load_split
    from diffcontact.simulator import simulator_for
    from diffcontact.systems import build_task

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("task", nargs="?", default="Gyro")
    ap.add_argument("--data", default="data")
    ap.add_argument("--chunks", type=int, default=3200, help="training chunks used (the first N)")
    ap.add_argument("--half-width", type=float, default=0.1, help="grid: truth ± this in μ and in e")
    ap.add_argument("--points", type=int, default=11, help="grid points per axis")
    ap.add_argument("--regs", nargs="+", type=float, default=[0.0], help="regularisations of A for the e scan")
    ap.add_argument("--no-grid", action="store_true", help="only the e scans (at the true μ)")
    ap.add_argument("--out", default="runs/loss_landscape.png")
    args = ap.parse_args()
    torch.set_num_threads(1)

    task = build_task(args.task)
    mu0, e0 = task.params.mu, task.params.e
    if not (bool((mu0 == mu0[0]).all()) and bool((e0 == e0[0]).all())):
        raise SystemExit(f"{args.task}: slots differ in μ or e; the landscape is for homogeneous tasks")
    mu_t, e_t = float(mu0[0]), float(e0[0])
    train = load_split(Path(args.data) / args.task, "train")
    x, v = (c[: args.chunks].to(torch.float64) for c in (train.chunk_x, train.chunk_v))

    def loss(mu: float, e: float, reg: float = 0.0) -> float:
        sim = simulator_for(task, reg=reg)
        p = task.params.replace(mu=torch.full_like(mu0, mu), e=torch.full_like(e0, e))
        return chunk_loss(sim, p, x, v, task.dt)

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    result: dict = {"task": args.task, "mu_true": mu_t, "e_true": e_t, "chunks": len(x)}
    started = time.perf_counter()
    hw, n = args.half_width, args.points
    mus = np.clip(np.linspace(mu_t - hw, mu_t + hw, n), 0.0, None)
    es = np.clip(np.linspace(e_t - hw, e_t + hw, n), 0.0, 1.0)
    if not args.no_grid:
        grid = np.array([[loss(m, e) for e in es] for m in mus])  # (μ, e)
        i, j = np.unravel_index(grid.argmin(), grid.shape)
        result["grid"] = {"mu": mus.tolist(), "e": es.tolist(), "loss": grid.tolist(), "argmin": [mus[i], es[j]]}
        print(f"grid argmin μ = {mus[i]:.4f}, e = {es[j]:.4f} (true {mu_t}, {e_t}); loss there {grid[i, j]:.3e}")
    scans = {}
    fine = np.clip(np.linspace(e_t - hw, e_t + hw, 4 * n - 3), 0.0, 1.0)
    for reg in args.regs:
        curve = np.array([loss(mu_t, e, reg) for e in fine])
        k = int(curve.argmin())
        at_truth = loss(mu_t, e_t, reg)
        scans[str(reg)] = {"e": fine.tolist(), "loss": curve.tolist(), "argmin_e": float(fine[k]), "at_truth": at_truth}
        print(f"reg {reg:g}: best e = {fine[k]:.4f} (true {e_t}), loss {curve[k]:.3e}; at the truth {at_truth:.3e}")
    result["e_scans"] = scans
    result["seconds"] = time.perf_counter() - started
    out.with_suffix(".json").write_text(json.dumps(result, indent=1))
    plot(result, out)
    print(f"wrote {out} and {out.with_suffix('.json')} ({result['seconds']:.0f} s)")


def plot(result: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = ("grid" in result) + 1
    fig, axes = plt.subplots(1, panels, figsize=(5 * panels, 4), squeeze=False)
    ax = axes[0, 0]
    if "grid" in result:
        g = result["grid"]
        floor = 1e-6  # (the loss is 0 at the truth: the data are this simulator's, float64)
        level = np.log10(np.maximum(np.array(g["loss"]), floor))
        cs = ax.contourf(g["e"], g["mu"], level, levels=np.linspace(np.log10(floor), level.max(), 21), cmap="viridis")
        fig.colorbar(cs, ax=ax, label="log10 loss")
        ax.plot([result["e_true"]], [result["mu_true"]], "r+", ms=12, label="truth")
        ax.set(xlabel="e", ylabel="μ", title=f"{result['task']}: loss around the truth (CM)")
        ax.legend()
        ax = axes[0, 1]
    for reg, s in result["e_scans"].items():
        ax.semilogy(s["e"], np.maximum(s["loss"], 1e-6), label=f"reg {float(reg):g} (best e {s['argmin_e']:.3f})")
    ax.axvline(result["e_true"], color="k", ls=":", label="true e")
    ax.set(xlabel="e (μ true)", ylabel="loss", title="e scan by regularisation of A")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=90)


if __name__ == "__main__":
    main()

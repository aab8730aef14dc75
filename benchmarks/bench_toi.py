"""Time of impact vs the published scheme on the benchmark tasks: cost per frame, energy and penetration.

For each task, N trajectories (seeded) x T frames at the task's dt with 1, 2, 4, 8 substeps per frame, the
published scheme (contacts at the end of each substep, velocity jump + penetration compensation) and the time of
impact (TOI, contacts at their time of impact; see docs/gradients.md). Printed as a Markdown table:

- ms / frame: wall time of the rollout (no gradient) per frame, after a 5-frame warm-up; both schemes of a row
  pair are timed one after the other in the same run, so their ratio is meaningful even on a loaded machine;
- energy gain: max over trajectories and frames of (E_t − E_0) / K_max (K_max the trajectory's largest kinetic
  energy); it should be <= 0 in every task (no task adds energy);
- |ΔE| (elastic frictionless tasks only: BP5-e, CP3-e, Gyro-e): max of |E_t − E_0| / K_max, which should be 0;
- worst penetration: the deepest negative gap over all candidates and frames (m; rad for the Rope's bend limits,
  whose stretch limits are in m), 0 when nothing penetrates.

    OMP_NUM_THREADS=1 python benchmarks/bench_toi.py --n 4 --out docs/figures/bench_toi.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import torch

import diffcontact
from diffcontact.simulator import simulator_for
from diffcontact.systems import BENCHMARK_TASKS, build_task

ELASTIC = ("BP5-e", "CP3-e", "Gyro-e")


def measure(name: str, n: int, frames: int, substeps: int, toi: bool, seed: int) -> dict:
    """One (task, substeps, scheme) cell: ms per frame, energy gain, |ΔE| (elastic tasks), worst penetration."""
    task = build_task(name)
    sim = simulator_for(task, time_of_impact=toi, substeps=substeps)
    state = task.sample(n, seed)
    with torch.no_grad():
        sim.rollout(state, task.params, task.dt, 5)  # warm-up, excluded
        t0 = time.perf_counter()
        x, v, hit = sim.rollout(state, task.params, task.dt, frames)
        seconds = time.perf_counter() - t0
        flat_x, flat_v = x.flatten(0, 1), v.flatten(0, 1)
        E = task.system.energy(task.params, flat_x, flat_v).reshape(n, frames)
        K = (E - task.params.potential(flat_x).reshape(n, frames)).amax(1, keepdim=True)
        gaps = task.system.detector.gaps(flat_x)
    rel = (E - E[:, :1]) / K
    return {
        "task": name,
        "substeps": substeps,
        "scheme": "TOI" if toi else "published",
        "ms_per_frame": 1e3 * seconds / (frames - 1),
        "energy_gain": rel.max().item(),
        "energy_abs": rel.abs().max().item() if name in ELASTIC else None,
        "penetration": max(0.0, -gaps.min().item()) if gaps.numel() else 0.0,
        "contact_frames": hit[:, 1:].float().mean().item(),
    }


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", nargs="*", default=list(BENCHMARK_TASKS))
    ap.add_argument("--n", type=int, default=4, help="trajectories per task")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--substeps", type=int, nargs="*", default=[1, 2, 4, 8])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="also write the rows as JSON (atomically)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    print(
        f"diffcontact {diffcontact.__version__}, torch {torch.__version__}, python {platform.python_version()}, "
        f"{platform.machine()}, {os.cpu_count()} CPUs, 1 torch thread; N = {args.n} x {args.frames} frames, "
        f"seed {args.seed}, float64, CM"
    )
    print("| task | substeps | scheme | ms / frame | TOI / published | energy gain | abs dE | worst penetration |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for name in args.tasks:
        for sub in args.substeps:
            pair = [measure(name, args.n, args.frames, sub, toi, args.seed) for toi in (False, True)]
            ratio = pair[1]["ms_per_frame"] / pair[0]["ms_per_frame"]
            for r in pair:
                r["toi_cost_ratio"] = ratio
                dE = "" if r["energy_abs"] is None else f"{r['energy_abs']:.1e}"
                print(
                    f"| {name} | {sub} | {r['scheme']} | {r['ms_per_frame']:.1f} | {ratio:.1f} | "
                    f"{r['energy_gain']:.1e} | {dE} | {r['penetration']:.1e} |",
                    flush=True,
                )
            rows.extend(pair)
    if args.out:
        meta = {"n": args.n, "frames": args.frames, "seed": args.seed, "torch": torch.__version__}
        path = Path(args.out)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(suffix=".json", dir=path.parent)
        with os.fdopen(fd, "w") as fh:
            json.dump({"meta": meta, "rows": rows}, fh, indent=1)
        os.replace(tmp, path)
    return rows


if __name__ == "__main__":
    main()

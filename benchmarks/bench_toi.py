"""Time of impact vs the published scheme on the benchmark tasks: cost per frame, energy and penetration.

For each task, N trajectories (seeded) x T frames at the task's dt with 1, 2, 4, 8 substeps per frame, the
published scheme (contacts at the end of each substep, velocity jump + penetration compensation) and the time of
impact (TOI, contacts at their time of impact; see docs/gradients.md). Printed as a Markdown table:

- ms / frame: wall time of the rollout (no gradient) per frame, after a 5-frame warm-up, the median of
  ``--repeats`` rollouts; the two schemes of a pair alternate in the same run (their ratio, TOI / published, is the
  cost of TOI; on a machine shared with other work the ratio is noisy: compare medians of several repeats);
- energy gain: max over trajectories and frames of (E_t − E_0) / K_max (K_max the trajectory's largest kinetic
  energy); it should be <= 0 in every task (no task adds energy);
- |ΔE| (elastic frictionless tasks only: BP5-e, CP3-e, Gyro-e): max of |E_t − E_0| / K_max, which should be 0;
- worst penetration: the deepest negative gap over all candidates and frames (m; rad for the Rope's bend limits,
  whose stretch limits are in m), 0 when nothing penetrates.

    OMP_NUM_THREADS=1 python benchmarks/bench_toi.py --n 4 --out docs/figures/bench_toi.json
"""

from __future__ import annotations

import diffcontact  # (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import torch

from diffcontact.simulator import simulator_for
from diffcontact.systems import BENCHMARK_TASKS, build_task

ELASTIC = ("BP5-e", "CP3-e", "Gyro-e")


def measure(name: str, n: int, frames: int, substeps: int, seed: int, repeats: int) -> list[dict]:
    """The (published, TOI) cells of one (task, substeps): ms per frame (median of ``repeats`` alternating
    rollouts), energy gain, |ΔE| (elastic tasks), worst penetration, fraction of frames in contact."""
    task = build_task(name)
    state = task.sample(n, seed)
    sims = [simulator_for(task, time_of_impact=toi, substeps=substeps) for toi in (False, True)]
    times: list[list[float]] = [[], []]
    results = []
    with torch.no_grad():
        for sim in sims:
            sim.rollout(state, task.params, task.dt, 5)  # warm-up, excluded
        for r in range(repeats):
            for i, sim in enumerate(sims):
                t0 = time.perf_counter()
                out = sim.rollout(state, task.params, task.dt, frames)
                times[i].append(time.perf_counter() - t0)
                if r == 0:
                    results.append(out)
    rows = []
    for i, (x, v, hit) in enumerate(results):
        flat_x, flat_v = x.flatten(0, 1), v.flatten(0, 1)
        with torch.no_grad():
            E = task.system.energy(task.params, flat_x, flat_v).reshape(n, frames)
            K = (E - task.params.potential_energy(flat_x).reshape(n, frames)).amax(1, keepdim=True)
            gaps = task.system.detector.gaps(flat_x)
        rel = (E - E[:, :1]) / K
        rows.append(
            {
                "task": name,
                "substeps": substeps,
                "scheme": "TOI" if i else "published",
                "ms_per_frame": 1e3 * statistics.median(times[i]) / (frames - 1),
                "energy_gain": rel.max().item(),
                "energy_abs": rel.abs().max().item() if name in ELASTIC else None,
                "penetration": max(0.0, -gaps.min().item()) if gaps.numel() else 0.0,
                "contact_frames": hit[:, 1:].float().mean().item(),
            }
        )
    return rows


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", nargs="*", default=list(BENCHMARK_TASKS))
    ap.add_argument("--n", type=int, default=4, help="trajectories per task")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--substeps", type=int, nargs="*", default=[1, 2, 4, 8])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=1, help="timed rollouts per scheme (median)")
    ap.add_argument("--out", default=None, help="also write the rows as JSON (atomically)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    print(
        f"diffcontact {diffcontact.__version__}, torch {torch.__version__}, python {platform.python_version()}, "
        f"{platform.machine()}, {os.cpu_count()} CPUs, 1 torch thread; N = {args.n} x {args.frames} frames, "
        f"seed {args.seed}, {args.repeats} timed repeats, float64, CM"
    )
    print("| task | substeps | scheme | ms / frame | TOI / published | energy gain | abs dE | worst penetration |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for name in args.tasks:
        for sub in args.substeps:
            pair = measure(name, args.n, args.frames, sub, args.seed, args.repeats)
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
        meta = {**vars(args), "torch": torch.__version__, "diffcontact": diffcontact.__version__}
        path = Path(args.out)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(suffix=".json", dir=path.parent)
        with os.fdopen(fd, "w") as fh:
            json.dump({"meta": meta, "rows": rows}, fh, indent=1)
        os.replace(tmp, path)
    return rows


if __name__ == "__main__":
    main()

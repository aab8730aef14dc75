"""Train every (task, model, seed) of the learning matrix with the defaults and collate the results (issue 13).

    python investigations/learning_matrix.py --jobs 2 --out runs/matrix            # 8 tasks x 4 models, seed 0
    python investigations/learning_matrix.py --models CM-CD-CLNN --seeds 1 2 ...    # more seeds
    python investigations/learning_matrix.py --collate-only --out runs/matrix       # the table of what has run

Each run is `diffcontact train TASK --model MODEL --seed S --out OUT/TASK/MODEL/seedS --no-progress` (no other
flag: the defaults), in its own process with one thread (OMP_NUM_THREADS=1, OMP_WAIT_POLICY=PASSIVE), ``--jobs`` at
a time; a run whose learned.json exists is not run again.  Datasets are generated first where missing.  The table
(markdown, to stdout and OUT/table.md) has one row per run: errors over the identifiable slots (learned.json), the
largest per-slot errors of slots with at least 20 identifying collisions, the inertia on the constraints' tangent
space up to the potential's scale, solver failures, skipped steps, best epoch and wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

TASKS = ["BP5-e", "CP3-e", "CP3", "Rope", "Gyro-e", "Gyro", "BP5", "BD5"]
MODELS = ["CM-CD-CLNN", "CM-CD-CHNN", "CMr-CD-CLNN", "CMr-CD-CHNN"]
# slots with at least this many identifying collisions in the training chunks (slipping for μ, set by the
# restitution bound for e): the per-slot goal (0.05)
MIN_COLLISIONS = 20


def run_one(task: str, model: str, seed: int, out: Path, data: str) -> tuple[str, float]:
    run = out / task / model / f"seed{seed}"
    if (run / "learned.json").is_file():
        return str(run), 0.0
    run.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE")
    cmd = ["diffcontact", "train", task, "--model", model, "--seed", str(seed), "--out", str(run), "--data", data]
    started = time.perf_counter()
    with open(run / "train.log", "w") as log:
        code = subprocess.call([*cmd, "--no-progress"], stdout=log, stderr=subprocess.STDOUT, env=env)
    if code:
        print(f"FAILED ({code}): {' '.join(cmd)} (see {run / 'train.log'})", file=sys.stderr)
    return str(run), time.perf_counter() - started


def slot_errors(item: dict, collisions: list[int]) -> float | None:
    """Largest |learned − true| over slots with ≥ MIN_COLLISIONS collisions (None: no such slot)."""
    errs = [abs(a - b) for a, b, c in zip(item["learned"], item["true"], collisions) if c >= MIN_COLLISIONS]
    return max(errs) if errs else None


def fmt(x: float | None, digits: int = 4) -> str:
    return "n/i" if x is None else f"{x:.{digits}f}"


def collate(out: Path, tasks: list[str] = TASKS, models: list[str] = MODELS) -> str:
    """The markdown table of every (task, model) cell, in that order: one row per finished run (every seed), and
    one "not run" row for a cell without any."""
    rows = [
        "| task | model | seed | μ err | e err | μ / e err, slots ≥ 20 ident. coll. | mass ratio err (rel)"
        " | inertia spread | solver failures | skipped | best epoch | time |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for model in models:
        for task in tasks:
            runs = sorted((out / task / model).glob("seed*/learned.json"))
            if not runs:
                rows.append(f"| {task} | {model} | — | not run |" + " |" * 8)
            rows.extend(_row(task, model, learned) for learned in runs)
    return "\n".join(rows)


def totals(out: Path, tasks: list[str] = TASKS, models: list[str] = MODELS) -> str:
    """One line: the summed wall time of the seed-0 runs of the matrix (Table 2) and of every run."""
    times = {
        (t, m, p.parent.name): json.loads(p.read_text())["wall_time_s"]
        for m in models
        for t in tasks
        for p in (out / t / m).glob("seed*/learned.json")
    }
    seed0 = [v for (t, m, seed), v in times.items() if seed == "seed0"]
    return (
        f"Seed-0 cells: {len(seed0)} of {len(tasks) * len(models)} run, {sum(seed0) / 3600:.2f} h of run time in all "
        f"(about {sum(seed0) / 7200:.2f} h two at a time); every run: {len(times)}, {sum(times.values()) / 3600:.2f} h."
    )


def _row(task: str, model: str, learned: Path) -> str:
    s = json.loads(learned.read_text())
    ratios = s["mass_ratio"]
    rel = max(abs(a / b - 1) for a, b in zip(ratios["learned"], ratios["true"]))
    hetero = len(set(s["mu"]["true"])) > 1 or len(set(s["e"]["true"])) > 1
    per_slot = (
        f"{fmt(slot_errors(s['mu'], s['collisions_slipping']), 3)} / "
        f"{fmt(slot_errors(s['e'], s['collisions_bound']), 3)}"
        if hetero
        else "—"
    )
    best = Path(s["best_checkpoint"]).stem.split("=")[-1] if s.get("best_checkpoint") else "?"
    return (
        f"| {task} | {model} | {learned.parent.name[4:]} | {fmt(s['mu']['max_abs_error'])} "
        f"| {fmt(s['e']['max_abs_error'])} | {per_slot} | {rel:.3%} | {s['inertia']['spread']:.3%} "
        f"| {s['solver_failures']} | {s['skipped_steps']} | {best} | {s['wall_time_s']:.0f} s |"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", nargs="+", default=TASKS)
    ap.add_argument("--models", nargs="+", default=MODELS)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--data", default="data")
    ap.add_argument("--out", default="runs/matrix")
    ap.add_argument("--collate-only", action="store_true")
    args = ap.parse_args()
    out = Path(args.out)
    if not args.collate_only:
        for task in args.tasks:
            if not (Path(args.data) / task).is_dir():
                subprocess.check_call(["diffcontact", "generate", task, "--out", args.data])
        jobs = [(t, m, s) for s in args.seeds for m in args.models for t in args.tasks]
        started = time.perf_counter()
        with ThreadPoolExecutor(args.jobs) as pool:
            for run, seconds in pool.map(lambda j: run_one(*j, out, args.data), jobs):
                print(f"{run}: {seconds:.0f} s", flush=True)
        print(f"matrix: {len(jobs)} runs, {time.perf_counter() - started:.0f} s with {args.jobs} jobs", flush=True)
    table = collate(out) + "\n\n" + totals(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "table.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()

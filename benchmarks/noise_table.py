"""The table of docs/results.md, "Noisy data": learned μ and e and the 5-step error of every run of one or more
`diffcontact reproduce --noise STD` folders, beside the published noise runs (spec H.6).

    T="-t BP5-e,CP3-e,CP3,Gyro-e,Gyro,Rope -m CM-CD-CLNN,CMr-CD-CLNN"
    diffcontact reproduce --noise 0.01 --out runs/noise-0.01 $T
    diffcontact reproduce --noise 0.05 --out runs/noise-0.05 $T
    python benchmarks/noise_table.py runs/noise-0.01 runs/noise-0.05
    python benchmarks/noise_table.py runs/noise-0.05 runs/again-0.05    # a later folder's runs replace the cells

Prints one markdown row per task, model and noise level: the learned and true μ and e, whether both are within 0.02
of the truth, the published values where there are any, the 5-step error on the clean test trajectories, and how the
run started its chunks (their first frames as recorded, or learned first states: by RMSprop's steps, the earlier
rule, or by trial steps, the default) and which checkpoint it kept. Seed 0. Where several folders hold a cell, the
last one given that has it evaluated makes the row; a cell that none has is a row that says so.
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (before torch: it sets OpenMP's wait policy)

# isort: split

import argparse
import json
from pathlib import Path

import torch

from diffcontact.eval import published
from diffcontact.eval.report import HOMOGENEOUS
from diffcontact.run_dir import RunDir

MODELS = ("CM-CD-CLNN", "CMr-CD-CLNN")


def first_states(run: RunDir) -> str:
    """How the run started its chunks: "recorded", or its first states learned ("RMSprop", "trial steps")."""
    if not run.read_config()["args"].get("first_state_chunks"):
        return "recorded"
    state = torch.load(run.last_checkpoint, map_location="cpu", weights_only=True)["state_dict"]
    return "learned, RMSprop" if "first_train.square" in state else "learned, trial steps"


def cells(out: Path) -> tuple[float, dict[tuple[str, str], str]]:
    """The noise of a `reproduce --noise` folder and the rows of its evaluated seed-0 runs, by (task, model)."""
    record = json.loads((out / "reproduce.json").read_text())
    noise = float(record["noise"])
    rows = {}
    for task in HOMOGENEOUS:
        for model in MODELS:
            run = RunDir.of_cell(out, task, model, 0)
            metrics = run.metrics() if run.config.is_file() else None
            if metrics is None or not run.learned.is_file():
                continue
            learned = run.read_learned()
            mu, e = learned["mu"]["learned"][0], learned["e"]["learned"][0]
            true = (learned["mu"]["true"][0], learned["e"]["true"][0])
            ok = "yes" if abs(mu - true[0]) <= 0.02 and abs(e - true[1]) <= 0.02 else "**no**"
            err = metrics["trajectory_error"]
            epoch = Path(learned.get("best_checkpoint") or "").stem.removeprefix("best-epoch=")
            rows[task, model] = (
                f"{mu:.4f}, {e:.4f} | {true[0]:g}, {true[1]:g} | {ok} | {{published}} | "
                f"{err['mean']:.3g} ± {err['ci95']:.2g} | {first_states(run)} | {epoch or '?'} |"
            )
    return noise, rows


def table(outs: list[Path]) -> list[str]:
    """The markdown rows of every noise level in ``outs`` (ascending), task and model, later folders first."""
    found: dict[float, dict[tuple[str, str], str]] = {}
    for out in outs:
        noise, rows = cells(out)
        found.setdefault(noise, {}).update(rows)
    lines = []
    for noise in sorted(found):
        for task in HOMOGENEOUS:
            for model in MODELS:
                pub = published.NOISE.get(noise, {}).get(task, {}).get(model)
                pub_text = f"{pub[0]:g}, {pub[1]:g}" if pub else "—"
                row = found[noise].get((task, model))
                body = row.format(published=pub_text) if row else f"not measured yet | | | {pub_text} | | | |"
                lines.append(f"| {noise:g} | {task} | {model} | {body}")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("outs", nargs="+", type=Path, help="`reproduce --noise` folders (later first)")
    args = ap.parse_args()
    print(
        "| noise | task | model | learned μ, e | true | within 0.02 | published μ, e | 5-step error | first states "
        "| checkpoint (epoch) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(table(args.outs)))


if __name__ == "__main__":
    main()

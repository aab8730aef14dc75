"""The table of docs/results.md, "Noisy data": learned μ and e and the 5-step error of every run of one or more
`diffcontact reproduce --noise STD` folders, beside the published noise runs (spec H.6).

    T="-t BP5-e,CP3-e,CP3,Gyro-e,Gyro,Rope -m CM-CD-CLNN,CMr-CD-CLNN"
    diffcontact reproduce --noise 0.01 --out runs/noise-0.01 $T
    diffcontact reproduce --noise 0.05 --out runs/noise-0.05 $T
    python benchmarks/noise_table.py runs/noise-0.01 runs/noise-0.05

Prints one markdown row per task, model and noise level: the learned and true μ and e, whether both are within 0.02
of the truth, the published values where there are any, and the 5-step error on the clean test trajectories; a run
not evaluated yet is a row that says so.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from diffcontact.eval import published
from diffcontact.eval.report import HOMOGENEOUS
from diffcontact.run_dir import RunDir

MODELS = ("CM-CD-CLNN", "CMr-CD-CLNN")


def rows(out: Path) -> list[str]:
    record = json.loads((out / "reproduce.json").read_text())  # (the noise, and the datasets' root if not OUT/data)
    noise = float(record["noise"])
    lines = []
    for task in HOMOGENEOUS:
        for model in MODELS:
            run = RunDir.of_cell(out, task, model, 0)
            pub = published.NOISE.get(noise, {}).get(task, {}).get(model)
            pub_text = f"{pub[0]:g}, {pub[1]:g}" if pub else "—"
            metrics = run.metrics()
            if metrics is None or not run.learned.is_file():
                lines.append(f"| {noise:g} | {task} | {model} | not measured yet | | | {pub_text} | |")
                continue
            learned = run.read_learned()
            mu, e = learned["mu"]["learned"][0], learned["e"]["learned"][0]
            true = (learned["mu"]["true"][0], learned["e"]["true"][0])
            ok = "yes" if abs(mu - true[0]) <= 0.02 and abs(e - true[1]) <= 0.02 else "**no**"
            err = metrics["trajectory_error"]
            lines.append(
                f"| {noise:g} | {task} | {model} | {mu:.4f}, {e:.4f} | {true[0]:g}, {true[1]:g} | {ok} | {pub_text} | "
                f"{err['mean']:.3g} ± {err['ci95']:.2g} |"
            )
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("outs", nargs="+", type=Path, help="folders of `diffcontact reproduce --noise STD`")
    args = ap.parse_args()
    print("| noise | task | model | learned μ, e | true | within 0.02 | published μ, e | 5-step error |")
    print("|---|---|---|---|---|---|---|---|")
    for out in args.outs:
        print("\n".join(rows(out)))


if __name__ == "__main__":
    main()

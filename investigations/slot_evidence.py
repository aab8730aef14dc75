"""Whether the slots a trained run marks identified (learned.json: std_error, identified, from the learned model
alone) are within 0.01 of the truth, and whether those it marks not identified are off (docs/results.md,
"Identifiability").

    python investigations/slot_evidence.py RUN [RUN ...]     # after diffcontact train (or summarize) on BP5, BD5

Prints per run and property: every slot with its learned and true values, standard error, the training chunks
that inform it, and the verdict: "ok" (identified and within 0.01, or not identified), "WRONG" (identified but off
by more than 0.01), "off, marked" (not identified and off: the marking did its job).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+")
    args = ap.parse_args()
    for run in args.runs:
        learned = json.loads((Path(run) / "learned.json").read_text())
        chunks = learned["evidence_chunks"]
        for key in ("mu", "e"):
            item = learned[key]
            wrong = marked = 0
            print(f"{run} {key}: slot, learned, true, std error, chunks, verdict")
            columns = zip(item["learned"], item["true"], item["std_error"], item["identified"])
            for s, (a, b, se, ok) in enumerate(columns):
                off = abs(a - b) > 0.01
                verdict = "WRONG" if ok and off else ("off, marked" if off else "ok")
                wrong += verdict == "WRONG"
                marked += verdict == "off, marked"
                se_text = "none" if se is None else f"{se:.2g}"
                print(f"  {s:3d} {a:8.4f} {b:8.4f} {se_text:>8} {chunks[s]:5d}  {verdict}")
            n_id = sum(item["identified"])
            print(f"  {n_id} of {len(item['learned'])} identified; {wrong} identified but off; {marked} off and marked")


if __name__ == "__main__":
    main()

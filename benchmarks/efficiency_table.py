"""The sample-efficiency table and figure of docs/results.md, "Sample efficiency on Rope200", from the cells of one
or more `diffcontact bench efficiency` folders (or their efficiency.json files), merged.

    diffcontact bench efficiency Rope200 -n 25 -n 50 -m CM-CD-CLNN --out runs/efficiency
    diffcontact bench efficiency Rope200 -n 1600 -m CM-CD-CLNN --out runs/efficiency-n1600
    python benchmarks/efficiency_table.py runs/efficiency runs/efficiency-n1600 --out runs/efficiency-all
    python benchmarks/efficiency_table.py docs/figures/efficiency.json runs/efficiency-n1600 --out docs/figures

Sweeps run as separate commands (one N or one model each, side by side) each write their own efficiency.json; this
sets their cells in one table: a cell measured in a later source replaces the same cell of an earlier one, and a
cell none has measured stays "not measured".  Writes OUT/efficiency.json (the merged table, its sources and each
source's epochs), efficiency.md and efficiency.png, and prints the table.
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (before torch: it sets OpenMP's wait policy)

# isort: split

import argparse
import json
from pathlib import Path

from diffcontact.errors import DiffContactError
from diffcontact.eval.efficiency import efficiency_markdown, write_outputs


def read(source: Path) -> dict:
    """A bench efficiency record (efficiency.json, or the folder that holds it)."""
    path = source / "efficiency.json" if source.is_dir() else source
    if not path.is_file():
        raise DiffContactError(f"{path}: no efficiency.json (run `diffcontact bench efficiency --out {source}`)")
    try:
        record = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise DiffContactError(f"{path} cannot be read as JSON: {err}") from err
    if not isinstance(record, dict) or "table" not in record or "task" not in record:
        raise DiffContactError(f"{path} is not a record of `diffcontact bench efficiency` (no task or table)")
    return record


def merge(records: list[dict]) -> tuple[str, dict[str, dict[int, dict | None]], dict[int, dict[str, int | None]]]:
    """The task, the merged table {model: {N: cell or None}} and the epochs of each measured cell's source."""
    tasks = {r["task"] for r in records}
    if len(tasks) != 1:
        raise DiffContactError(f"the sources are sweeps of different tasks: {sorted(tasks)}")
    table: dict[str, dict[int, dict | None]] = {}
    epochs: dict[int, dict[str, int | None]] = {}
    for record in records:
        for model, row in record["table"].items():
            merged = table.setdefault(model, {})
            for n, cell in row.items():
                if cell is not None or int(n) not in merged:
                    merged[int(n)] = cell
                if cell is not None:
                    epochs.setdefault(int(n), {})[model] = record.get("epochs_by_size", {}).get(n, {}).get(model)
    return tasks.pop(), table, epochs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sources", nargs="+", type=Path, help="bench efficiency folders or efficiency.json files")
    parser.add_argument("--out", type=Path, required=True, help="folder of the merged efficiency.{json,md,png}")
    args = parser.parse_args()
    try:
        task, table, epochs = merge([read(s) for s in args.sources])
    except DiffContactError as err:
        raise SystemExit(f"error: {err}") from None
    args.out.mkdir(parents=True, exist_ok=True)
    record = {
        "task": task,
        "sources": [str(s) for s in args.sources],
        "epochs_by_size": {str(n): e for n, e in sorted(epochs.items())},
    }
    write_outputs(args.out, task, table, epochs, record)
    print(efficiency_markdown(task, table, epochs))


if __name__ == "__main__":
    main()

"""Put the report of a `diffcontact reproduce` folder into docs/results.md (between its report markers).

    python benchmarks/publish_report.py runs/reproduction

Rewrites OUT/report.md and its figures from the runs evaluated so far (every task and model of the benchmark, the
others marked as not measured yet), copies the figures under 200 kB to docs/figures/reproduction/, and replaces the
text between ``<!-- report:start -->`` and ``<!-- report:end -->`` of docs/results.md with the report: figure links
point at the copies, links to run files (GIFs, not committed) are shown as paths under OUT.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
from pathlib import Path

from diffcontact.eval.report import write_report
from diffcontact.files import write_text
from diffcontact.models import ALL_MODELS
from diffcontact.systems.registry import BENCHMARK_TASKS

START, END = "<!-- report:start -->", "<!-- report:end -->"
MAX_FIGURE = 200_000  # bytes: larger figures stay in OUT (docs/ holds small PNGs only)


def publish(out: Path, docs: Path) -> Path:
    """Regenerate OUT's report and put it into docs/results.md; returns the page's path."""
    settings = json.loads((out / "reproduce.json").read_text())
    report = write_report(out, list(BENCHMARK_TASKS), list(ALL_MODELS), [0], settings).read_text()
    figures = docs / "figures" / "reproduction"
    figures.mkdir(parents=True, exist_ok=True)
    for png in sorted((out / "figures").glob("*.png")):
        if png.stat().st_size <= MAX_FIGURE:
            shutil.copyfile(png, figures / png.name)

    def figure(match: re.Match) -> str:
        name = match.group(2)
        if (figures / name).is_file() and (out / "figures" / name).stat().st_size <= MAX_FIGURE:
            return f"![{match.group(1)}](figures/reproduction/{name})"
        return f"(figure `{out / 'figures' / name}`, not committed: over 200 kB)"

    body = re.sub(r"!\[([^\]]*)\]\(figures/([^)]+)\)", figure, report)
    body = re.sub(r"\[([^\]]+)\]\((runs/[^)]+)\)", lambda m: f"{m.group(1)}: `{out / m.group(2)}`", body)
    body = re.sub(r"^(#+) ", r"#\1 ", body, flags=re.M)  # (one level down: the report is a section of the page)
    body = body.replace("## Reproduction report", "## The reproduction report", 1)
    page = docs / "results.md"
    text = page.read_text()
    if START not in text or END not in text:
        raise SystemExit(f"{page} has no {START} … {END} markers")
    head, rest = text.split(START, 1)
    tail = rest.split(END, 1)[1]
    write_text(page, f"{head}{START}\n{body.strip()}\n{END}{tail}")
    return page


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="the reproduce folder (its --out)")
    parser.add_argument("--docs", type=Path, default=Path("docs"))
    args = parser.parse_args()
    print(publish(args.out, args.docs))


if __name__ == "__main__":
    main()

"""The learned values and the evaluation of several runs of one task and model (seeds), side by side: each value's
runs, mean, sample standard deviation and range. ``diffcontact spread RUN...``."""

from __future__ import annotations

import statistics
from collections.abc import Sequence
from pathlib import Path

from diffcontact.errors import ConfigError
from diffcontact.run_dir import RunDir

LEARNED_LISTS = ("mu", "e", "mass_ratio", "moments", "centre_of_mass")  # learned.json items with a "learned" list
METRICS = ("position_error_pct", "rotation_error_deg", "penetration_pct", "same_final_face")  # measured tosses


def _row(values: list[float]) -> dict:
    std = statistics.stdev(values) if len(values) > 1 else None
    return {"runs": values, "mean": statistics.fmean(values), "std": std, "min": min(values), "max": max(values)}


def _scalars(learned: dict, metrics: dict | None) -> dict[str, float]:
    """A run's values by name: ``mu[0]``, ``moments[2]``, ``g``, ``table_height_m``, ``eval.position_error_pct``."""
    out = {}
    for key in LEARNED_LISTS:
        for i, v in enumerate((learned.get(key) or {}).get("learned") or []):
            out[f"{key}[{i}]"] = float(v)
    if isinstance(learned.get("g"), (int, float)):
        out["g"] = float(learned["g"])
    if isinstance(learned.get("table_height_m"), dict):
        out["table_height_m"] = float(learned["table_height_m"]["value"])
    for key, value in (metrics or {}).items():
        if key in METRICS and isinstance(value, (int, float)):
            out[f"eval.{key}"] = float(value)
    return out


def spread(runs: Sequence[str | Path], eval_name: str = "eval") -> dict:
    """The runs' task, model, seeds and, per value (keys as in :func:`_scalars`, the evaluation's metrics from
    ``RUN/eval_name/metrics.json`` where every run has one), ``{"runs", "mean", "std", "min", "max"}``.

    Every run must be a finished training of the same task and model (ConfigError naming the run otherwise); a value
    that not every run has is left out and named in ``"missing"``."""
    if not runs:
        raise ConfigError("spread: give at least one run directory")
    dirs = [RunDir(r) for r in runs]
    configs = [d.read_config()["args"] for d in dirs]
    first = (configs[0]["task"], configs[0]["model"])
    for d, c in zip(dirs, configs, strict=True):
        if (c["task"], c["model"]) != first:
            raise ConfigError(f"{d.path} is a run of {c['model']} on {c['task']}, not {first[1]} on {first[0]}")
    values = [_scalars(d.read_learned(), d.metrics(eval_name)) for d in dirs]
    names = list(dict.fromkeys(k for v in values for k in v))
    common = [k for k in names if all(k in v for v in values)]
    return {
        "task": first[0],
        "model": first[1],
        "runs": [str(d.path) for d in dirs],
        "seeds": [c.get("seed") for c in configs],
        "values": {k: _row([v[k] for v in values]) for k in common},
        "missing": [k for k in names if k not in common],
    }


def spread_table(result: dict) -> str:
    """:func:`spread`'s result as a Markdown table: one row per value, one column per run, then mean, std, range."""
    seeds = [f"seed {s}" for s in result["seeds"]]
    lines = [
        f"{result['model']} on {result['task']}, {len(seeds)} runs",
        "",
        "| value | " + " | ".join(seeds) + " | mean | std | range |",
        "|---|" + "---|" * (len(seeds) + 3),
    ]
    for name, row in result["values"].items():
        std = "—" if row["std"] is None else f"{row['std']:.4g}"
        cells = [f"{v:.4g}" for v in row["runs"]] + [f"{row['mean']:.4g}", std, f"{row['max'] - row['min']:.4g}"]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if result["missing"]:
        lines += ["", "Not in every run: " + ", ".join(result["missing"])]
    return "\n".join(lines)

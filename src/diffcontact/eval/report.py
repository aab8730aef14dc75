"""OUT/report.md of a reproduction: Table 2, per-slot vectors, mass ratios and the 5-step errors beside the published
values, and the figures (paper Figs. 3, 4, 5 and 7-13) under OUT/figures/.  Every cell of the matrix has a row: a
run not evaluated is marked missing, failed or not run, never left out."""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

import diffcontact
from diffcontact.eval import published
from diffcontact.eval.evaluate import evaluated
from diffcontact.files import write_text
from diffcontact.models import MODEL_NAMES
from diffcontact.run_dir import ROLLOUT, ROLLOUT_GIF, RunDir

HOMOGENEOUS = ("BP5-e", "CP3-e", "CP3", "Rope", "Gyro-e", "Gyro")


def _status(out: Path, task: str, model: str, seed: int) -> str:
    """What became of a cell without metrics: failed (with why), interrupted or not run."""
    run = RunDir.of_cell(out, task, model, seed)
    try:
        record = json.loads(run.reproduce_record.read_text())
    except (OSError, ValueError):
        record = {}
    if record.get("status") == "failed":
        return f"failed: {record.get('error', '')}"
    if run.last_checkpoint.is_file():
        return "not measured yet (training interrupted; resumes from its last checkpoint)"
    return "not measured yet (not run)"


def _num(x: float | None, digits: int = 4) -> str:
    return "—" if x is None else f"{x:.{digits}f}"


def _err(mean: float, half: float | None) -> str:
    return f"{mean:.3g}" + ("" if half is None else f" ± {half:.2g}")


def _pct(x: float) -> str:
    """A relative deviation as a percentage; "diverged" for +inf, powers of ten beyond 1000 %."""
    if x == float("inf"):
        return "diverged"
    return f"{x:.2%}" if x < 10 else f"{100 * x:.1e} %"


def write_report(out: str | Path, tasks: list[str], models: list[str], seeds: list[int], settings: dict) -> Path:
    """Write OUT/report.md and its figures from the evaluated runs under OUT/runs/; returns the report's path.

    The tables and figures use the first seed; the run table lists every seed."""
    from diffcontact.eval import plots

    out = Path(out)
    figures = out / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    seed = seeds[0]
    metrics = {
        (t, m, s): evaluated(RunDir.of_cell(out, t, m, s).path, t, m) for t in tasks for m in models for s in seeds
    }
    first = {(t, m): metrics[t, m, seed] for t in tasks for m in models}
    missing = {(t, m): _status(out, t, m, seed) for (t, m), v in first.items() if v is None}
    total = sum(s["seconds"] for s in settings.get("sessions", []))
    lines = [
        "# Reproduction report",
        "",
        f"Written {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} by `diffcontact reproduce` "
        f"(diffcontact {diffcontact.__version__}, torch {torch.__version__}, Python {platform.python_version()}).",
        f"Command of the last session: `{settings.get('sessions', [{}])[-1].get('command') or 'reproduce()'}`; "
        f"{len(settings.get('sessions', []))} session(s), {total:.0f} s of wall time in all. Datasets: "
        f"`{settings.get('data', 'data')}`.",
        f"Runs evaluated: {sum(v is not None for v in metrics.values())} of {len(metrics)}; every table has a row or "
        "cell for each run, the others marked as not measured yet.",
        "",
        "Metrics (the paper's): relative error ‖ẑ − z‖/‖z‖ of each frame over positions and velocities; the ground "
        "truth is the exact contact model (CM) in float64 from the test trajectories' initial states, for every model. "
        "Tables and figures show seed " + str(seed) + ".",
        "",
    ]
    if settings.get("noise"):
        lines += [
            f"**Noisy data**: observation noise of std {settings['noise']:g} on the training and validation chunks "
            "(diffcontact.data.noise); the test trajectories, and so every error below, are clean.",
            "",
        ]
    if settings.get("n_train"):
        lines += [f"**Training set**: {settings['n_train']} trajectories per task.", ""]
    if settings.get("quick"):
        lines += [
            "**Quick mode**: tiny datasets, one epoch, short rollouts. The numbers check the pipeline, not the method.",
            "",
        ]
    lines += _runs_table(out, tasks, models, seeds, metrics)
    lines += _table2(tasks, models, first, missing, settings.get("noise", 0.0))
    lines += _slots(tasks, models, first, missing)
    lines += _mass_ratios(tasks, models, first, missing)

    # Fig. 3
    cells = {
        t: {m: (v["trajectory_error"]["mean"], v["trajectory_error"]["ci95"]) for m in models if (v := first[t, m])}
        for t in tasks
    }
    lines += ["## Fig. 3: 5-step trajectory error", ""]
    if any(cells.values()):
        plots.error_bars(cells, figures / "fig3_errors.png", published.TRAJECTORY_ERROR)
        lines += ["![Fig. 3](figures/fig3_errors.png)", ""]
    lines += [
        "Sum of the relative errors of frames 0-4, mean over the test trajectories ± the 95 % interval; "
        "the paper's values in brackets where published (CM-CD-CLNN on four tasks, every model on the ropes of "
        "50-200 nodes).",
        "",
        "| task | " + " | ".join(models) + " |",
        "|---|" + "---|" * len(models),
    ]
    for t in tasks:
        row = []
        for m in models:
            cell = _err(*cells[t][m]) if m in cells[t] else missing[t, m]
            pub = published.TRAJECTORY_ERROR.get(t, {}).get(m)
            row.append(cell + (f" (published {_err(*pub)})" if pub else ""))
        lines.append(f"| {t} | " + " | ".join(row) + " |")
    lines.append("")

    # Fig. 4
    curves = {t: {m: v["error_curve"] for m in models if (v := first[t, m])} for t in tasks}
    dts = {t: v["dt"] for (t, m), v in first.items() if v}
    lines += ["## Fig. 4: relative error over the rollout", ""]
    if any(curves.values()):
        plots.error_curves({t: c for t, c in curves.items() if c}, dts, figures / "fig4_curves.png")
        lines += ["![Fig. 4](figures/fig4_curves.png)", ""]
    lines += ["| task | model | frame 4 | last frame (frame) |", "|---|---|---|---|"]
    for t in tasks:
        for m in models:
            c = curves[t].get(m)
            shown = f"{c[min(4, len(c) - 1)]:.3g} | {c[-1]:.3g} ({len(c) - 1})" if c else f"{missing[t, m]} | —"
            lines.append(f"| {t} | {m} | {shown} |")
    lines.append("")

    # Fig. 5
    elastic = [t for t in tasks if t in published.ELASTIC]
    lines += ["## Fig. 5: true energy along predicted trajectories", ""]
    panels = {}
    for t in elastic:
        series = {m: v["energy"] for m in models if (v := first[t, m])}
        if series:
            panels[t] = {"truth": next(iter(series.values()))["shown_true"]}
            panels[t].update({m: e["shown_predicted"] for m, e in series.items()})
    if panels:
        plots.energy_panels(panels, dts, figures / "fig5_energy.png")
        lines += ["![Fig. 5](figures/fig5_energy.png)", ""]
    lines += [
        "Largest |E(ẑ_t) − E(z_t)| over the frames shown (the true energy of prediction and truth) relative to the "
        "trajectory's energy in motion (its largest true kinetic energy), mean and largest over the test "
        "trajectories; the paper's elastic tasks are those plotted.",
        "",
        "| task | model | frames | mean | max |",
        "|---|---|---|---|---|",
    ]
    for t in tasks:
        for m in models:
            v = first[t, m]
            e = v["energy"] if v else None
            if e:
                shown = f"{e['frames']} | {_pct(e['max_rel_deviation_mean'])} | {_pct(e['max_rel_deviation_max'])}"
            else:
                shown = f"— | {missing[t, m]} | —"
            lines.append(f"| {t} | {m} | {shown} |")
    lines.append("")
    lines += _rollouts(out, tasks, models, seed, first, missing, figures)
    path = out / "report.md"
    write_text(path, "\n".join(lines) + "\n")
    return path


def _runs_table(out, tasks, models, seeds, metrics) -> list[str]:
    lines = [
        "## Runs",
        "",
        "| task | model | seed | status | training (s) | evaluation (s) | 5-step error |",
        "|---|---|---|---|---|---|---|",
    ]
    for t in tasks:
        for m in models:
            for s in seeds:
                v = metrics[t, m, s]
                train, ev = RunDir.of_cell(out, t, m, s).times()
                status = "done" if v else _status(out, t, m, s)
                err = _err(v["trajectory_error"]["mean"], v["trajectory_error"]["ci95"]) if v else "—"
                lines.append(f"| {t} | {m} | {s} | {status} | {_num(train, 0)} | {_num(ev, 0)} | {err} |")
    return [*lines, ""]


def _learned(v: dict | None, key: str) -> list[float] | None:
    item = ((v or {}).get("learned") or {}).get(key)
    return item["learned"] if item else None


def _table2(tasks, models, first, missing, noise: float = 0.0) -> list[str]:
    """Table 2 (learned μ, e) beside the published values: Table 2 itself, or with noisy data the published noise
    runs (H.6; "—" where none was published)."""
    shown = [t for t in tasks if t in HOMOGENEOUS]
    cms = [m for m in models if m in published.TABLE2["BP5-e"]]
    title = f" on data with noise {noise:g}" if noise else ""
    lines = [f"## Table 2: learned μ, e (homogeneous tasks){title}", ""]
    if not shown or not cms:
        return [*lines, f"No homogeneous task ({', '.join(HOMOGENEOUS)}) or contact model in this reproduction.", ""]
    source = published.NOISE.get(noise, {}) if noise else published.TABLE2
    lines += [
        f"Ours / the paper's {'runs on noisy data (H.6)' if noise else 'Table 2'}, each as μ, e.",
        "",
        "| task (true μ, e) | " + " | ".join(cms) + " |",
        "|---|" + "---|" * len(cms),
    ]
    for t in shown:
        true = None
        row = []
        for m in cms:
            v = first[t, m]
            mu, e = _learned(v, "mu"), _learned(v, "e")
            if v and v.get("learned"):
                true = (v["learned"]["mu"]["true"][0], v["learned"]["e"]["true"][0])
            ours = f"{mu[0]:.4f}, {e[0]:.4f}" if mu and e else missing.get((t, m), "no learned.json")
            pub = source.get(t, {}).get(m)
            row.append(f"{ours} / " + (f"{pub[0]:g}, {pub[1]:g}" if pub else "—"))
        head = f"{t} ({true[0]:g}, {true[1]:g})" if true else t
        lines.append(f"| {head} | " + " | ".join(row) + " |")
    return [*lines, ""]


def _slots(tasks, models, first, missing) -> list[str]:
    lines = ["## Per-slot μ and e (heterogeneous tasks)", ""]
    cms = [m for m in models if m in MODEL_NAMES]
    hetero = [t for t in tasks if t in published.SLOTS]
    if not hetero or not cms:
        return [
            *lines,
            f"No heterogeneous task ({', '.join(published.SLOTS)}) or contact model in this reproduction.",
            "",
        ]
    for t in hetero:
        for key, name in (("mu", "μ"), ("e", "e")):
            vecs = {m: _learned(first[t, m], key) for m in cms}
            truth = next(((first[t, m] or {})["learned"][key]["true"] for m in cms if vecs[m]), None)
            pub = published.SLOTS[t][key]
            marks = {m: ((first[t, m] or {}).get("learned") or {}).get(key, {}).get("identified") for m in cms}
            lines += [f"### {t}: learned {name} per contact slot (10 pairs, then 20 ball-wall)", ""]
            if any(ok and not all(ok) for ok in marks.values()):
                lines += [
                    "A value in brackets is one its run marks not identified (learned.json: its standard error "
                    "from the training data is above 0.005).",
                    "",
                ]
            lines += [
                "| slot | true | published CM-CD-CLNN | " + " | ".join(cms) + " |",
                "|---|---|---|" + "---|" * len(cms),
            ]
            for i in range(len(pub)):
                ours = [
                    (_num(vec[i]) if not marks[m] or marks[m][i] else f"({_num(vec[i])})")
                    if (vec := vecs[m])
                    else missing.get((t, m), "—")
                    for m in cms
                ]
                lines.append(f"| {i} | {_num(truth[i] if truth else None)} | {pub[i]:.4f} | " + " | ".join(ours) + " |")
            lines.append("")
    return lines


def _mass_ratios(tasks, models, first, missing) -> list[str]:
    lines = [
        "## Learned mass ratios (mass / mass of body 0)",
        "",
        "| task | model | true | ours | published |",
        "|---|---|---|---|---|",
    ]
    for t in tasks:
        for m in models:
            v = first[t, m]
            ours = _learned(v, "mass_ratio")
            pub = published.MASS_RATIO.get(t, {}).get(m)
            pub_s = ", ".join(f"{r:.4g}" for r in pub) if pub else "—"
            if ours:
                true = ", ".join(f"{r:.4g}" for r in v["learned"]["mass_ratio"]["true"])
                lines.append(f"| {t} | {m} | {true} | {', '.join(f'{r:.4f}' for r in ours)} | {pub_s} |")
            else:
                lines.append(f"| {t} | {m} | — | {missing.get((t, m), 'not learned by this model')} | {pub_s} |")
    return [*lines, ""]


def _rollouts(out, tasks, models, seed, first, missing, figures) -> list[str]:
    from diffcontact.eval.animate import rollout_strip
    from diffcontact.systems.registry import build_task

    lines = [
        "## Rollouts (paper Figs. 7-13)",
        "",
        "Every 5th frame of one test trajectory: the truth, then each model.",
    ]
    for t in tasks:
        rows, contact, dt = {}, None, None
        for m in models:
            v = first[t, m]
            if not v:
                continue
            with np.load(RunDir.of_cell(out, t, m, seed).eval_dir() / ROLLOUT) as arrays:
                if contact is None:
                    rows["truth"], contact, dt = arrays["x"], arrays["contact"], v["dt"]
                rows[m] = arrays["x_hat"]
        lines += ["", f"### {t}", ""]
        if rows:
            if contact is None or dt is None:  # (unreachable: read with the truth's row)
                raise AssertionError(f"{t}: the truth's rollout has no contact flags or dt")
            rollout_strip(build_task(t).system, rows, contact, figures / f"rollout_{t}.png", dt)
            lines += [f"![{t}](figures/rollout_{t}.png)", ""]
        for m in models:
            v = first[t, m]
            gif = RunDir.of_cell(out, t, m, seed).eval_dir() / ROLLOUT_GIF if v else None
            if gif and gif.is_file():
                lines.append(f"- {m}: [truth beside prediction (GIF)]({os.path.relpath(gif, out)})")
            else:
                lines.append(f"- {m}: {missing.get((t, m), 'no GIF')}")
    return [*lines, ""]

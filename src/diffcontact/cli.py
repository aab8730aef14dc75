"""Command line: thin subcommands that parse arguments and call the library."""

from __future__ import annotations

import typer

app = typer.Typer(
    help="diffcontact: differentiable contact models for learning rigid-body dynamics.",
    no_args_is_help=True,
    add_completion=False,
)
bench_app = typer.Typer(help="Benchmarks (medians and ratios measured in one run).", no_args_is_help=True)
app.add_typer(bench_app, name="bench")


@bench_app.command("solver")
def bench_solver(
    batch: list[int] = typer.Option([1, 128, 800], "--batch", "-b", help="Batch sizes B."),
    contacts: list[int] = typer.Option([1, 2, 3, 5, 19], "--contacts", "-k", help="Contact counts K."),
    dims: list[int] = typer.Option([2, 3], "--dim", "-d", help="Contact-space dimensions d."),
    repeats: int = typer.Option(5, help="Timed repetitions of our solver (median reported)."),
    reference: bool = typer.Option(True, help="Also time the cvxpylayers reference (needs the extra)."),
    ref_max_batch: int = typer.Option(
        800, help="Time the reference on at most this many problems per setting (its cost is per problem)."
    ),
    seed: int = typer.Option(0, help="Seed of the random instances."),
    out: str = typer.Option("", help="Also write the table as Markdown to this file."),
) -> None:
    """Forward+backward time per problem of the contact solver against the cvxpylayers reference."""
    from diffcontact.bench.solver import run_solver_benchmark

    run_solver_benchmark(
        batches=batch,
        contacts=contacts,
        dims=dims,
        repeats=repeats,
        reference=reference,
        ref_max_batch=ref_max_batch,
        seed=seed,
        out=out or None,
    )


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    app()

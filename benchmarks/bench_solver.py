"""Contact-solver benchmark (same as `diffcontact bench solver`): python benchmarks/bench_solver.py [--help]."""

from diffcontact.cli import app

if __name__ == "__main__":
    app(["bench", "solver"])

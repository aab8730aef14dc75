"""Simulation benchmark (same as `diffcontact bench simulate`): 1000 trajectories x 100 frames for each of the
8 benchmark tasks, CM, float64, 2 threads (goal: all 8 in under 5 minutes).

Run:  python benchmarks/bench_simulate.py [--help | --n N --steps T --task NAME ...]
"""

import sys

from diffcontact.cli import app

if __name__ == "__main__":
    app(["bench", "simulate", *sys.argv[1:]])

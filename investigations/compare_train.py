"""The training step of two source trees side by side: `diffcontact bench train` of each, alternating task by task
in one run, and the losses of a few fixed-seed training steps of each (the same to rounding?).

    python investigations/compare_train.py --base /path/to/old/src [--tasks BP5-e CP3] [--threads 1] [--repeats 5]

The new tree is this checkout's ``src``.  Each measurement is its own process (``python -m diffcontact.cli``), with
PYTHONPATH set to the tree; the load average is printed with every row, as the machine may be shared.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

NEW = Path(__file__).resolve().parents[1] / "src"
TASKS = ("BP5-e", "BP5", "CP3-e", "CP3", "BD5", "Rope", "Gyro-e", "Gyro")

LOSSES = """
import inspect, json, sys, torch
from diffcontact.threads import set_threads
from diffcontact.bench.train import synthetic_batch
from diffcontact.train.module import ContactLightningModule
task, model, batch, steps = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
set_threads(1)
data, _ = synthetic_batch(task, model, batch, 0)
settings = dict(seed=0, dtype="float32", lr=1e-2)
if "config" in inspect.signature(ContactLightningModule).parameters:  # (a tree whose module takes a TrainConfig)
    from diffcontact.train.config import TrainConfig
    m = ContactLightningModule(TrainConfig(task, model, **settings))
else:
    m = ContactLightningModule(task, model, **settings)
opt = m.configure_optimizers()
opt = opt["optimizer"] if isinstance(opt, dict) else opt
losses = []
for _ in range(steps):
    loss = m.loss(data)
    opt.zero_grad()
    loss.backward()
    opt.step()
    m.learned.project_()
    losses.append(float(loss))
print(json.dumps(losses))
"""


def _env(tree: Path, threads: int) -> dict:
    return dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS=str(threads), OMP_WAIT_POLICY="PASSIVE")


def bench(tree: Path, task: str, model: str, args) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bench.json"
        cmd = [sys.executable, "-m", "diffcontact.cli", "bench", "train", task, "--models", model]
        cmd += ["--batch", str(args.batch), "--repeats", str(args.repeats), "--threads", str(args.threads)]
        subprocess.run(cmd + ["--out", str(out)], env=_env(tree, args.threads), check=True, capture_output=True)
        return json.loads(out.read_text())["rows"][0]


def losses(tree: Path, task: str, model: str, args) -> list[float]:
    cmd = [sys.executable, "-c", LOSSES, task, model, str(args.loss_batch), str(args.steps)]
    res = subprocess.run(cmd, env=_env(tree, 1), capture_output=True, text=True)
    if res.returncode:
        raise SystemExit(f"{tree}: {res.stderr}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", type=Path, required=True, help="The old tree's src folder.")
    p.add_argument("--tasks", nargs="*", default=list(TASKS))
    p.add_argument("--model", default="CM-CD-CLNN")
    p.add_argument("--batch", type=int, default=200)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--steps", type=int, default=3, help="Training steps whose losses are compared (0: none).")
    p.add_argument("--loss-batch", type=int, default=50)
    p.add_argument("--no-timing", action="store_true")
    args = p.parse_args()
    print(f"base {args.base}, new {NEW}; {args.model}, batch {args.batch}, {args.threads} thread(s), float32")
    print("| task | step base (ms) | step new (ms) | speed-up | CPU base (ms) | CPU new (ms) | speed-up (CPU) "
          "| contact share base | new | dynamics base | new | max rel. loss difference | load |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for task in args.tasks:
        rel = float("nan")
        if args.steps:
            la, lb = losses(args.base, task, args.model, args), losses(NEW, task, args.model, args)
            rel = max(abs(a - b) / abs(a) for a, b in zip(la, lb))
        if args.no_timing:
            print(f"| {task} | | | | | | | | | | | {rel:.1e} | {os.getloadavg()[0]:.1f} |", flush=True)
            continue
        a, b = bench(args.base, task, args.model, args), bench(NEW, task, args.model, args)
        a2, b2 = bench(args.base, task, args.model, args), bench(NEW, task, args.model, args)  # (ABAB)
        sa, sb = min(a["step"], a2["step"]), min(b["step"], b2["step"])
        ca, cb = min(a["cpu"], a2["cpu"]), min(b["cpu"], b2["cpu"])
        print(
            f"| {task} | {1e3 * sa:.0f} | {1e3 * sb:.0f} | {sa / sb:.2f}× | {1e3 * ca:.0f} | {1e3 * cb:.0f} | "
            f"{ca / cb:.2f}× | {a['contact_share']:.0%} | "
            f"{b['contact_share']:.0%} | {1e3 * a['dynamics']:.0f} | {1e3 * b['dynamics']:.0f} | {rel:.1e} | "
            f"{os.getloadavg()[0]:.1f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()

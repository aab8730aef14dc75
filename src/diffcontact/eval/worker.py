"""One cell of ``diffcontact reproduce`` in its own process: train (``diffcontact.train.run.train_run``, the default
preset, resuming from the run's last checkpoint if there is one) unless already trained, then evaluate.

    python -m diffcontact.eval.worker TASK MODEL SEED RUN_DIR DATA_ROOT [--train] [--epochs E] [--batch-size B]
                                      [--frames T] [--no-pictures]
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path


def die_with_parent() -> None:
    """Have the kernel kill this process when the process that started it dies (Linux; elsewhere nothing): a cell
    whose driver or cluster worker was killed leaves no trainer behind to hold the run's lock against its retry."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import os
    import signal

    parent = os.getppid()
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # (PR_SET_PDEATHSIG)
    if os.getppid() != parent:  # (the parent died before the call)
        os._exit(1)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m diffcontact.eval.worker", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("task")
    p.add_argument("model")
    p.add_argument("seed", type=int)
    p.add_argument("run", type=Path)
    p.add_argument("data", type=Path)
    p.add_argument("--train", action="store_true", help="Train first (resuming from checkpoints/last.ckpt).")
    p.add_argument("--epochs", type=int, default=None, help="Epochs (default: the preset's).")
    p.add_argument("--batch-size", type=int, default=None, help="Chunks per batch (default: the preset's).")
    p.add_argument("--frames", type=int, default=None, help="Frames rolled out in the evaluation.")
    p.add_argument("--no-pictures", action="store_true", help="Evaluate without the GIF and figures.")
    args = p.parse_args(argv)

    import torch

    from diffcontact.errors import DiffContactError
    from diffcontact.eval.evaluate import evaluate_run
    from diffcontact.run_dir import RunDir
    from diffcontact.train.run import train_run

    die_with_parent()
    run = RunDir(args.run)
    try:
        if args.train and run.learned.is_file():  # (a retry after the training ended: never twice)
            print(f"{args.run}: trained already (learned.json); evaluating only", flush=True)
        elif args.train:
            settings = dict(
                seed=args.seed, out=args.run, data_root=args.data, epochs=args.epochs, batch_size=args.batch_size
            )
            last = run.last_checkpoint
            if last.is_file():
                try:  # (only a checkpoint that does not load is thrown away: an error in training is not)
                    torch.load(last, map_location="cpu", weights_only=False)
                except Exception as err:  # (damaged by the interruption: train afresh)
                    print(f"{last} does not load ({type(err).__name__}: {err}); training from the start", flush=True)
                    for part in (run.checkpoints, run.logs):  # (a fresh run is refused beside another's checkpoints)
                        shutil.rmtree(part, ignore_errors=True)
            train_run(args.task, args.model, resume=last.is_file(), progress=False, **settings)
        m = evaluate_run(
            args.run, task=args.task, data_root=args.data, frames=args.frames, pictures=not args.no_pictures
        )
    except (DiffContactError, FloatingPointError) as err:
        print(f"{type(err).__name__}: {err}", file=sys.stderr)
        return 2
    if "trajectory_error" in m:
        print(f"{args.task} {args.model} seed {args.seed}: 5-step error {m['trajectory_error']['mean']:.4g}")
    else:  # (measured tosses)
        print(f"{args.task} {args.model} seed {args.seed}: position error {m['position_error_pct']:.4g} % of the width")
    return 0


if __name__ == "__main__":
    sys.exit(main())

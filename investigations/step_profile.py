"""Where a training step goes at a given batch: its wall and CPU time, the torch operations it runs, and the
operations that take the most time (torch's profiler), for the model and settings that ``diffcontact train`` makes.

    python investigations/step_profile.py BP5-e --batch 50      # the default preset's batch
    python investigations/step_profile.py BP5-e --batch 200     # the published preset's
    python investigations/step_profile.py BP5-e --by-function   # also the forward's torch calls by function

One thread, float32, synthetic chunks as ``diffcontact bench train`` makes them; 3 untimed steps, 10 timed, 3
profiled (the profiler's own overhead inflates its times: read them as shares).
"""

from __future__ import annotations

import diffcontact as dc  # isort: split

import argparse
import collections
import sys
import time

from torch.overrides import TorchFunctionMode
from torch.profiler import ProfilerActivity, profile

from diffcontact.bench.train import StepTimer, synthetic_batch
from diffcontact.threads import set_threads


class _CallsByFunction(TorchFunctionMode):
    """Counts the torch functions called, by the innermost function of the package that called them."""

    def __init__(self) -> None:
        super().__init__()
        self.counts: collections.Counter[str] = collections.Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        frame = sys._getframe(1)
        while frame is not None and "diffcontact" not in frame.f_code.co_filename:
            frame = frame.f_back
        where = f"{frame.f_code.co_filename.split('diffcontact/')[-1]}:{frame.f_code.co_name}" if frame else "other"
        self.counts[where] += 1
        return func(*args, **(kwargs or {}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("task")
    parser.add_argument("--batch", type=int, default=50)
    parser.add_argument("--model", default="CM-CD-CLNN")
    parser.add_argument("--rows", type=int, default=20, help="Operations listed.")
    parser.add_argument("--by-function", action="store_true", help="Also count the forward's calls by function.")
    args = parser.parse_args()
    set_threads(1)
    data, colliding = synthetic_batch(args.task, args.model, args.batch)
    timer = StepTimer(args.task, args.model, data)
    for _ in range(3):
        timer.step()
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(10):
        timer.step()
    wall, cpu = (time.perf_counter() - wall) / 10, (time.process_time() - cpu) / 10
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(3):
            timer.step()
    events = prof.key_averages()
    calls = sum(e.count for e in events) / 3
    head = f"diffcontact {dc.__version__}: {args.task} {args.model}, {args.batch} chunks ({colliding:.0%} colliding)"
    print(f"{head}: step {1e3 * wall:.1f} ms wall, {1e3 * cpu:.1f} ms CPU; {calls:.0f} torch operations a step")
    print(events.table(sort_by="self_cpu_time_total", row_limit=args.rows))
    if args.by_function:
        with _CallsByFunction() as calls_by:
            timer.module.loss(timer.batch)
        print(f"the forward's torch calls from Python: {sum(calls_by.counts.values())}; by function:")
        for where, count in calls_by.counts.most_common(args.rows):
            print(f"{count:7d}  {where}")


if __name__ == "__main__":
    main()

"""Where a training step goes at a given batch: its wall and CPU time, the torch operations it runs, and the
operations that take the most time (torch's profiler), for the model and settings that ``diffcontact train`` makes.

    python investigations/step_profile.py BP5-e --batch 50      # the default preset's batch
    python investigations/step_profile.py BP5-e --batch 200     # the published preset's

One thread, float32, synthetic chunks as ``diffcontact bench train`` makes them; 3 untimed steps, 10 timed, 3
profiled (the profiler's own overhead inflates its times: read them as shares).
"""

from __future__ import annotations

import diffcontact as dc  # isort: split

import argparse
import time

from torch.profiler import ProfilerActivity, profile

from diffcontact.bench.train import StepTimer, synthetic_batch
from diffcontact.threads import set_threads


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("task")
    parser.add_argument("--batch", type=int, default=50)
    parser.add_argument("--model", default="CM-CD-CLNN")
    parser.add_argument("--rows", type=int, default=20, help="Operations listed.")
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


if __name__ == "__main__":
    main()

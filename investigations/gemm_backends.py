"""How fast would a training step's matrix products run on another BLAS?

    python investigations/gemm_backends.py Rope200 IN-CP-SP
    python investigations/gemm_backends.py Rope200 CM-CD-CLNN BP5-e:CM-CD-CLNN --batch 50

For each TASK MODEL pair (or TASK:MODEL): one training step as ``diffcontact bench train`` makes it (float32, one
thread, synthetic chunks), profiled with its products' shapes (``aten::mm``, ``aten::addmm``); then every distinct
product shape (M×K by K×N) timed alone, contiguous, with torch's own BLAS (``torch.mm``), with oneDNN (tensors
converted beforehand, ``mkldnn_linear``) and with numpy's BLAS (OpenBLAS in the PyPI wheels). Prints the step's
CPU time, its products' profiled time, and the same products' time at each backend's rate. Times are CPU seconds of
this process (one thread); stop other work on the machine for a clean figure.
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (before torch: it sets OpenMP's wait policy)

# isort: split

import argparse
import os
import time
from collections import Counter

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402  (after the BLAS's thread count)
import torch  # noqa: E402
from torch.profiler import ProfilerActivity, profile  # noqa: E402

from diffcontact.bench.train import StepTimer, synthetic_batch  # noqa: E402


def product_shapes(task: str, model: str, batch: int) -> tuple[Counter, float, float]:
    """The (M, K, N) of every product of one training step with its count; the products' and the step's CPU s."""
    data, _ = synthetic_batch(task, model, batch)
    timer = StepTimer(task, model, data)
    for _ in range(2):
        timer.step()
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        cpu = timer.step()["cpu"]
    shapes: Counter = Counter()
    product_s = 0.0
    for ev in prof.events():
        if ev.name not in ("aten::mm", "aten::addmm"):
            continue
        dims = [s for s in ev.input_shapes if len(s) == 2]
        a, b = dims[-2], dims[-1]  # (addmm: bias, mat1, mat2)
        shapes[(a[0], a[1], b[1])] += 1
        product_s += ev.self_cpu_time_total / 1e6
    return shapes, product_s, cpu


def seconds(f, min_time: float = 0.05) -> float:
    """CPU seconds per call of ``f`` (repeated for at least ``min_time``)."""
    f()
    n, t0 = 0, time.process_time()
    while (elapsed := time.process_time() - t0) < min_time:
        f()
        n += 1
    return elapsed / n


def backend_times(M: int, K: int, N: int) -> dict[str, float]:
    """CPU seconds of one (M×K)(K×N) float32 product: torch, oneDNN, numpy."""
    a, b = torch.randn(M, K), torch.randn(K, N)
    an, bn = a.numpy(), b.numpy()
    am, wm, bias = a.to_mkldnn(), b.T.contiguous().to_mkldnn(), torch.zeros(N).to_mkldnn()
    return {
        "torch": seconds(lambda: torch.mm(a, b)),
        "oneDNN": seconds(lambda: torch._C._nn.mkldnn_linear(am, wm, bias)),
        "numpy": seconds(lambda: an @ bn),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("pairs", nargs="+", help="TASK MODEL pairs, or TASK:MODEL")
    ap.add_argument("--batch", type=int, default=50, help="chunks (or a baseline's pairs) per step")
    args = ap.parse_args()
    torch.set_num_threads(1)
    words = [p for w in args.pairs for p in w.split(":")]
    if len(words) % 2:
        ap.error("give TASK MODEL pairs")
    print(f"torch {torch.__version__}, numpy {np.__version__}; CPU s, one thread, batch {args.batch}")
    print("| task | model | step | products (profiled) | at torch's rate | at oneDNN's | at numpy's | ≥ 2,000 rows |")
    print("|---|---|---|---|---|---|---|---|")
    for task, model in zip(words[::2], words[1::2]):
        shapes, product_s, cpu = product_shapes(task, model, args.batch)
        total = Counter()
        for (M, K, N), n in shapes.items():
            for name, s in backend_times(M, K, N).items():
                total[name] += n * s
        tall = sum(n for (M, _, _), n in shapes.items() if M >= 2000)
        print(
            f"| {task} | {model} | {cpu:.3f} | {product_s:.3f} | {total['torch']:.3f} | {total['oneDNN']:.3f} | "
            f"{total['numpy']:.3f} | {tall} of {sum(shapes.values())} |"
        )


if __name__ == "__main__":
    main()

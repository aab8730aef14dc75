"""Memory does not grow with training steps: no autograd graph is kept alive by a reference cycle.

A tensor kept as an attribute of an autograd Function's ``ctx`` that is also one of the Function's outputs makes a
cycle output → grad_fn → ctx → output through C++ objects, which Python's garbage collector cannot break: every
step then leaks its graph. These tests count what stays alive; they time nothing.
"""

from __future__ import annotations

import gc
import weakref

import pytest
import torch

from diffcontact.bench.train import StepTimer, synthetic_batch


def _live_tensors() -> int:
    gc.collect()
    return sum(1 for o in gc.get_objects() if issubclass(type(o), torch.Tensor))  # (type(o): no attribute of o read)


def test_the_flat_projection_frees_its_outputs():
    """Outputs of FlatProjection (with a graph) are freed as soon as the caller drops them, without a collection."""
    from diffcontact.solver.least_norm import FlatProjection

    gen = torch.Generator().manual_seed(0)
    F = torch.randn(3, 4, 2, generator=gen, dtype=torch.float64, requires_grad=True)
    used = torch.ones(3, 4, dtype=torch.bool)
    A = F @ F.mT
    out = FlatProjection.apply(0.5 * (A + A.mT), torch.ones(3, 4, dtype=torch.float64), used, 1e-6, torch.arange(3))
    refs = [weakref.ref(t) for t in out]
    out[0].sum().backward()  # the backward pass still works from what was saved
    assert F.grad is not None and bool(torch.isfinite(F.grad).all())
    gc.disable()  # freed by reference counting alone: no cycle left for the collector (which cannot see through C++)
    try:
        del out, A
        alive = [r() is not None for r in refs]
    finally:
        gc.enable()
    assert not any(alive), f"outputs of FlatProjection outlived their graph: {alive}"


@pytest.mark.slow
def test_gyroscope_training_steps_keep_the_live_tensor_count_flat():
    """Steps of CM-CD-CLNN on gyroscope chunks (whose singular effective mass goes through the flat projection):
    after a warm-up the number of live tensors does not grow (the leaking code added about 48 a step)."""
    torch.manual_seed(0)
    batch, colliding = synthetic_batch("Gyro", "CM-CD-CLNN", 24, seed=0)
    assert colliding > 0.2  # the steps do go through contacts
    timer = StepTimer("Gyro", "CM-CD-CLNN", batch)
    for _ in range(3):
        timer.step()
    before = _live_tensors()
    for _ in range(8):
        timer.step()
    after = _live_tensors()
    assert after - before <= 5, f"live tensors grew from {before} to {after} over 8 training steps"

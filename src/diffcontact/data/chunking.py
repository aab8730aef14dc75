"""Choose one training window ("chunk") per trajectory so that about half of the chunks contain a collision.

The published benchmark's rule: windows of ``length`` frames at every start; a window is usable only if its
first frame is not a collision frame. A trajectory is *marked* (wants a colliding chunk) if it has a collision and
either fewer than half of the trajectories collide, or a coin with probability 0.5 / ratio says so. A marked
trajectory with a colliding window gets one (uniformly at random); otherwise a window without collision is taken,
or a colliding one when there is none.
"""

from __future__ import annotations

import torch

from diffcontact.errors import DatasetError


def select_chunks(
    contact: torch.Tensor, length: int, generator: torch.Generator, p_collision: float = 0.5
) -> tuple[torch.Tensor, torch.Tensor]:
    """Window starts (N,) int64 and "chunk contains a collision" flags (N,) bool for contact flags (N, T) bool.

    All random draws come from ``generator`` (first the marks (N,), then the window choice (N, W)).
    Raises DatasetError if a trajectory has no usable window (every start is a collision frame) or T < length.
    """
    if contact.dim() != 2 or contact.dtype != torch.bool:
        raise DatasetError(f"contact must be a (N, T) bool tensor, got {tuple(contact.shape)} {contact.dtype}")
    n, frames = contact.shape
    if not 2 <= length <= frames:
        raise DatasetError(f"chunk length = {length} is not in [2, T = {frames}]")
    if not 0.0 < p_collision <= 1.0:
        raise DatasetError(f"p_collision = {p_collision:g} is not in (0, 1]")
    windows = contact.unfold(1, length, 1)  # (N, W, L)
    start_ok = ~windows[..., 0]
    hits = windows.any(-1)
    set_a = start_ok & ~hits  # no collision in the window
    set_b = start_ok & hits  # at least one collision after a collision-free first frame
    has_a, has_b = set_a.any(1), set_b.any(1)
    if not bool((has_a | has_b).all()):
        bad = torch.nonzero(~(has_a | has_b)).flatten().tolist()
        raise DatasetError(
            f"trajectories {bad[:10]} have no window of {length} frames whose first frame is not a collision frame"
        )
    collides = contact.any(1)
    ratio = float(collides.double().mean()) if n else 0.0
    coin = torch.rand(n, generator=generator, dtype=torch.float64)
    marked = collides & ((ratio < p_collision) | (coin < p_collision / max(ratio, 1e-300)))
    use_b = (marked & has_b) | ~has_a
    allowed = torch.where(use_b[:, None], set_b, set_a)
    # a uniform choice among the allowed windows: the largest of i.i.d. uniforms over the allowed entries
    score = torch.rand(allowed.shape, generator=generator, dtype=torch.float64).masked_fill(~allowed, -1.0)
    starts = score.argmax(1)
    return starts, hits.gather(1, starts[:, None]).squeeze(1)


def gather_windows(a: torch.Tensor, starts: torch.Tensor, length: int) -> torch.Tensor:
    """Frames ``starts[i] : starts[i] + length`` of each trajectory: a (N, T, ...) -> (N, length, ...)."""
    idx = starts[:, None] + torch.arange(length)  # (N, L)
    idx = idx.reshape(idx.shape + (1,) * (a.dim() - 2)).expand(-1, -1, *a.shape[2:])
    return a.gather(1, idx)

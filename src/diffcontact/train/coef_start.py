"""Where the learned μ and e start: drawn at random (the default preset), or scanned (``coef_start = "scan"``).

The loss of long rollouts with impacts is rough in μ and e at small scales and smooth at large ones: on the real
cube tosses (80-frame windows) the validation loss rises steadily from e = 0.07 to e = 0.9 (0.0072 → 0.0213 at
μ = 0.124), yet its gradient changes sign between e = 0.66 and 0.67, and a run started at e = 0.615 stayed at
e = 0.68 with four times the loss of one started at 0.45.  The scan evaluates the training loss on a coarse grid of
(μ, e) over a seeded subset of the training windows and starts from the least; gradient descent refines from there.
"""

from __future__ import annotations

import math

import torch

from diffcontact.errors import ConfigError

MU_GRID = (0.05, 0.15, 0.3, 0.6)
E_GRID = (0.1, 0.35, 0.6, 0.85)
SCAN_WINDOWS = 64  # training windows the scan's loss is taken over (at most)


@torch.no_grad()
def scan_coefficients(module, chunk_x: torch.Tensor, chunk_v: torch.Tensor, seed: int) -> dict:
    """Set ``module``'s learned μ and e (every slot alike) to the point of ``MU_GRID`` × ``E_GRID`` with the least
    L1 loss over ``SCAN_WINDOWS`` training windows drawn with ``seed``; returns the record of the scan (grid, losses,
    chosen point).  chunk_x, chunk_v: (N, L, P, d) training windows.  Needs projected μ and e (the default preset)."""
    params = module.learned
    if params is None or params.n_slots == 0:
        raise ConfigError("coef_start = 'scan' needs a model that learns μ and e")
    if params.mu_transform != "projected" or params.e_transform != "projected":
        raise ConfigError("coef_start = 'scan' needs mu_transform and e_transform 'projected' (the default preset)")
    gen = torch.Generator().manual_seed(seed)
    pick = torch.randperm(len(chunk_x), generator=gen)[:SCAN_WINDOWS]
    batch = (chunk_x[pick], chunk_v[pick])
    was_training, mu0, e0 = module.training, params.mu_raw.clone(), params.e_raw.clone()
    module.eval()
    losses = []
    try:
        for mu in MU_GRID:
            for e in E_GRID:
                params.mu_raw.fill_(mu)
                params.e_raw.fill_(e)
                losses.append({"mu": mu, "e": e, "loss": float(module.loss(batch, "l1"))})
    finally:
        module.train(was_training)
    finite = [c for c in losses if math.isfinite(c["loss"])]
    if not finite:
        params.mu_raw.copy_(mu0)
        params.e_raw.copy_(e0)
        raise ConfigError("coef_start = 'scan': the loss is not finite at any point of the grid")
    best = min(finite, key=lambda c: c["loss"])
    params.mu_raw.fill_(best["mu"])
    params.e_raw.fill_(best["e"])
    return {"windows": len(pick), "seed": seed, "grid": losses, "chosen": {"mu": best["mu"], "e": best["e"]}}

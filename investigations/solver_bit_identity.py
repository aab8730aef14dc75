"""Bit identity of the contact solver across a change of its code: solve a fixed set of batches (with gradients)
and save the answers, then compare two saves.

    python investigations/solver_bit_identity.py save before.pt                        # the code as installed
    PYTHONPATH=OTHER/src python investigations/solver_bit_identity.py save after.pt    # another tree, its kernel
    python investigations/solver_bit_identity.py compare before.pt after.pt            # built in place there

The batches: seeded random problems (K = 1 … 40 contacts, d = 1, 2, 3; A regular, and singular with q in its
range; μ in [0, 1.5) with zeros; μ from 0.1 to 1e6 with lower bounds and inactive contacts), each with the
gradients of a weighted sum of f w.r.t. A, q and μ, and the captured simulation batches of tests/data.
"""

from __future__ import annotations

import diffcontact as dc  # isort: split

import sys
from pathlib import Path

import torch

DATA = Path(__file__).resolve().parents[1] / "tests" / "data"
CAPTURED = ("solver_captured.pt", "solver_face_compression.pt", "solver_face_sliding_restitution.pt")


def answers() -> dict[str, torch.Tensor]:
    """Every batch's solution (and gradients), flattened, by name."""
    out = {}
    g = torch.Generator().manual_seed(0)
    for K in (1, 2, 3, 5, 9, 19, 40):
        for d in (1, 2, 3):
            for cols in (K * d + 2, max(2, K * d // 2 + 1)):
                J = torch.randn(64, K * d, cols, dtype=torch.float64, generator=g)
                A = J @ J.mT
                q = torch.randn(64, K * d, dtype=torch.float64, generator=g)
                if cols < K * d:  # (singular A: q in its range, so that the problem is bounded)
                    q = -(J @ torch.randn(64, cols, 1, dtype=torch.float64, generator=g)).squeeze(-1)
                mu = torch.rand(64, K, dtype=torch.float64, generator=g) * 1.5
                mu[:8] = 0.0
                A.requires_grad_(True), q.requires_grad_(True), mu.requires_grad_(True)
                f = dc.solve_cone_qp(A, q, mu, lower=None, active=None, on_failure="count")
                weights = torch.linspace(0.5, 1.5, K * d, dtype=torch.float64)
                grads = torch.autograd.grad((f * weights).sum(), (A, q, mu))
                out[f"K{K}-d{d}-rank{cols}"] = torch.cat([f.detach().flatten(), *(x.flatten() for x in grads)])
    for K, d in ((2, 3), (5, 3), (9, 3), (5, 2)):  # (μ 0.1 … 1e6, bounds, inactive contacts: every stage)
        J = torch.randn(64, K * d, K * d + 2, dtype=torch.float64, generator=g)
        A, q = J @ J.mT, torch.randn(64, K * d, dtype=torch.float64, generator=g)
        mu = 10 ** (7 * torch.rand(64, K, dtype=torch.float64, generator=g) - 1)
        lower = 0.1 * torch.rand(64, K, dtype=torch.float64, generator=g)
        active = torch.rand(64, K, generator=g) > 0.2
        A.requires_grad_(True), q.requires_grad_(True), mu.requires_grad_(True)
        f = dc.solve_cone_qp(A, q, mu, lower, active, on_failure="count")
        grads = torch.autograd.grad((f * torch.linspace(0.5, 1.5, K * d, dtype=torch.float64)).sum(), (A, q, mu))
        out[f"K{K}-d{d}-large-mu"] = torch.cat([f.detach().flatten(), *(x.flatten() for x in grads)])
    for name in CAPTURED:
        cases = torch.load(DATA / name, weights_only=True)
        for i, c in enumerate(cases if isinstance(cases, list) else [cases]):
            f = dc.solve_cone_qp(c["A"], c["q"], c["mu"], c.get("lower"), c.get("active"), on_failure="count")
            out[f"{name}-{i}"] = f.flatten()
    return out


def main(argv: list[str]) -> int:
    if len(argv) == 2 and argv[0] == "save":
        saved = answers()
        torch.save(saved, argv[1])
        print(f"{argv[1]}: {len(saved)} batches, solver from {Path(dc.__file__).parent}")
        return 0
    if len(argv) == 3 and argv[0] == "compare":
        a, b = (torch.load(p, weights_only=True) for p in argv[1:])
        differ = sorted(k for k in a.keys() & b.keys() if not torch.equal(a[k], b[k]))
        missing = sorted(a.keys() ^ b.keys())
        print(f"{len(a.keys() & b.keys()) - len(differ)} batches bit-identical, {len(differ)} differ: {differ}")
        if missing:
            print(f"in one save only: {missing}")
        return 1 if differ or missing else 0
    print(__doc__)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""Batched contact detection: the active candidates of every batch element and their Jacobian rows.

All candidate kinds of a system share one contact-space dimension dc (the largest of its kinds); rows of a
kind with fewer rows are zero-padded and the contact is made frictionless, so one solver call has one d.
Only batch elements with at least one active contact are kept, and their contacts are compacted into the
first K_c slots (K_c = the largest active count in the batch) with an ``active`` mask.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.nn.functional import pad

from diffcontact.contact.kinds import ContactKind
from diffcontact.state import with_anchors


@dataclass(frozen=True)
class ContactSet:
    """Active contacts of the colliding batch elements.

    index: (B',) batch indices; active: (B', K_c) bool; gap: (B', K_c) (0 where inactive);
    J: (B', K_c dc, D) contact Jacobian (rows of inactive contacts are 0); slot: (B', K_c) index into μ, e;
    frictionless: (B', K_c) bool (limit-like contacts padded to dc rows).
    """

    index: torch.Tensor
    active: torch.Tensor
    gap: torch.Tensor
    J: torch.Tensor
    slot: torch.Tensor
    frictionless: torch.Tensor
    dc: int


class Detector:
    """All contact candidates of a system, concatenated (K_max of them), with static index tensors."""

    def __init__(self, kinds: tuple[ContactKind, ...], n_points: int, anchors: torch.Tensor, d: int):
        self.kinds = tuple(k for k in kinds if k.count > 0)
        self.P, self.d, self.anchors = n_points, d, anchors
        self.dc = max((k.dc for k in self.kinds), default=d)
        self.count = sum(k.count for k in self.kinds)
        # static point index (K_max, m) of every candidate's Jacobian terms, m the most of any kind; anchors and
        # padding point to column P, which is dropped
        self._m = max((k.cols.shape[1] for k in self.kinds), default=0)
        self._cols = torch.cat(
            [pad(torch.where(k.cols < n_points, k.cols, n_points), (0, self._m - k.cols.shape[1]), value=n_points)
             for k in self.kinds]
        ) if self.kinds else torch.zeros(0, 0, dtype=torch.long, device=anchors.device)  # fmt: skip
        if self.kinds:
            self.slot = torch.cat([k.slot for k in self.kinds])
            self.frictionless = torch.cat(
                [torch.full((k.count,), k.dc < self.dc, device=k.slot.device) for k in self.kinds]
            )
        else:
            self.slot = torch.zeros(0, dtype=torch.long, device=anchors.device)
            self.frictionless = torch.zeros(0, dtype=torch.bool, device=anchors.device)

    def extend(self, x: torch.Tensor) -> torch.Tensor:
        """Positions with the fixed anchors appended: (B, P, d) -> (B, P + n_anchors, d)."""
        return with_anchors(x, self.anchors)

    def gaps(self, x: torch.Tensor) -> torch.Tensor:
        """Signed gaps of all K_max candidates (B, K_max); negative means in contact."""
        ext = self.extend(x)
        if not self.kinds:
            return x.new_zeros(x.shape[0], 0)
        return torch.cat([k.evaluate(ext, rows=False)[0] for k in self.kinds], dim=1)

    def jacobian(self, x: torch.Tensor, order: torch.Tensor | None = None) -> torch.Tensor:
        """Rows (B, K, dc, D) in the (P, d) layout, anchors dropped, of every candidate (K = K_max), or of the
        candidates ``order`` (B, K) (indices into K_max) of each batch element.

        Each candidate's few terms are placed at its points (a scatter): the cost is that of writing the rows, not
        of a product over all points.
        """
        ext = self.extend(x)
        B = x.shape[0]
        terms = []
        for kind in self.kinds:  # a handful of declared kinds, not contacts
            _, vals = kind.evaluate(ext, rows=True)  # (B, K, m, dck, d)
            if vals is None:
                raise TypeError(f"{type(kind).__name__}.evaluate(rows=True) returned no rows")
            terms.append(pad(vals, (0, 0, 0, self.dc - kind.dc, 0, self._m - vals.shape[2])))
        vals = torch.cat(terms, dim=1)  # (B, K_max, m, dc, d)
        cols = self._cols.to(x.device).expand(B, -1, -1)  # (static: follows x's device)
        if order is not None:
            vals = torch.gather(vals, 1, order[:, :, None, None, None].expand(-1, -1, *vals.shape[2:]))
            cols = torch.gather(cols, 1, order[:, :, None].expand(-1, -1, self._m))
        K = cols.shape[1]
        index = cols[:, :, None, :, None].expand(B, K, self.dc, self._m, self.d)
        rows = torch.zeros(B, K, self.dc, self.P + 1, self.d, dtype=x.dtype, device=x.device)
        rows = rows.scatter_add(3, index, vals.transpose(2, 3))
        return rows[:, :, :, : self.P].reshape(B, K, self.dc, self.P * self.d)

    def detect(self, x: torch.Tensor) -> ContactSet | None:
        """The active contacts at positions x (B, P, d), or None if no batch element is in contact."""
        if not self.kinds:
            return None
        with torch.no_grad():
            gap_all = self.gaps(x)
        return self.select(x, gap_all < 0, gap_all)

    def select(self, x: torch.Tensor, hit: torch.Tensor, gap_all: torch.Tensor) -> ContactSet | None:
        """The contacts marked by ``hit`` (B, K_max) at positions x (B, P, d), with gaps ``gap_all`` (B, K_max)
        (used by the penetration target), or None if no batch element has a marked contact."""
        with torch.no_grad():
            index = torch.nonzero(hit.any(dim=1)).flatten()
            if index.numel() == 0:
                return None
            hit = hit[index]
            k_c = int(hit.sum(1).max())
            order = torch.argsort((~hit).to(torch.int8), dim=1, stable=True)[:, :k_c]  # active first
            active = torch.gather(hit, 1, order)
            gap = torch.gather(gap_all[index], 1, order) * active
        J = self.jacobian(x[index], order)
        J = (J * active[:, :, None, None]).reshape(len(index), k_c * self.dc, -1)
        return ContactSet(
            index=index,
            active=active,
            gap=gap,
            J=J,
            slot=self.slot.to(order.device)[order],
            frictionless=self.frictionless.to(order.device)[order],
            dc=self.dc,
        )

    def rates(self, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Gaps (B, K_max) and their rates dg/dt = ∇g(x)·v (B, K_max) at (x, v) (m/s), without gradient.

        The rate is the Jacobian-vector product of the gaps, by the double-backward trick.
        """
        if not self.kinds:
            return x.new_zeros(x.shape[0], 0), x.new_zeros(x.shape[0], 0)
        with torch.enable_grad():
            xg = x.detach().requires_grad_(True)
            g = self.gaps(xg)
            u = torch.zeros_like(g, requires_grad=True)
            (gx,) = torch.autograd.grad(g, xg, grad_outputs=u, create_graph=True)
            (rate,) = torch.autograd.grad(gx, u, grad_outputs=v.detach())
        return g.detach(), rate.detach()

"""The contact solver as the physics uses it: tolerances, the failure policy and counters, around one back end.

``ContactSolver()`` raises :class:`~diffcontact.errors.ContactSolverError` on a failed problem (the default: no
silent zero impulses); ``ContactSolver(on_failure="count")`` continues with zero impulses for the failed problems,
logs a warning and counts them by status (training, the simulation benchmark).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from diffcontact.solver.policy import POLICY
from diffcontact.solver.problem import solve_cone_qp
from diffcontact.solver.status import Status, is_failure

log = logging.getLogger(__name__)

ON_FAILURE = ("raise", "count")
_N_STATUS = len(Status)
_FAILURE_CODES = is_failure(np.arange(_N_STATUS))  # ((N,) bool: the codes of failures)
_CONVERGED = int(Status.CONVERGED)


@dataclass(eq=False)
class ContactSolver:
    """Solves batches of contact cone QPs with ``backend`` (signature and options of
    :func:`~diffcontact.solver.solve_cone_qp`, which is the default) and counts what it did.

    tol, acceptable_tol, max_iter: passed to the back end; on_failure: "raise" or "count" (see the module doc).
    Counters: ``calls`` (batches solved), ``counts`` (problems by :class:`Status`, all codes).
    """

    tol: float = POLICY.tol
    acceptable_tol: float = POLICY.acceptable_tol
    max_iter: int = POLICY.max_iter
    on_failure: Literal["raise", "count"] = "raise"
    backend: Callable = field(default=solve_cone_qp, repr=False)
    calls: int = field(default=0, init=False)
    counts: np.ndarray = field(default_factory=lambda: np.zeros(len(Status), dtype=np.int64), init=False, repr=False)

    def __post_init__(self):
        if self.on_failure not in ON_FAILURE:
            raise ValueError(f"on_failure must be one of {list(ON_FAILURE)}, got {self.on_failure!r}")

    def __call__(
        self,
        A: torch.Tensor,
        q: torch.Tensor,
        mu: torch.Tensor,
        lower: torch.Tensor | None = None,
        active: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """f (B, K·d) for a batch (A: (B, K·d, K·d), q: (B, K·d), mu, lower, active: (B, K)); see ``backend``."""
        f, info = self.backend(
            A,
            q,
            mu,
            lower,
            active,
            tol=self.tol,
            acceptable_tol=self.acceptable_tol,
            max_iter=self.max_iter,
            on_failure=self.on_failure,
            return_info=True,
        )
        self.calls += 1
        counts = np.bincount(info.status.numpy(), minlength=_N_STATUS)
        self.counts += counts
        if counts[_CONVERGED] < len(f):  # (all converged, the common case, needs no more: 3 µs of a small call)
            failed = counts * _FAILURE_CODES
            if np.count_nonzero(failed):
                names = {Status(c).name: int(n) for c, n in enumerate(failed) if n}
                log.warning("contact solver failed for %s of %d problems; their impulses are zero", names, len(f))
        return f

    @property
    def problems(self) -> int:
        """Problems solved so far (batch elements over all calls)."""
        return int(self.counts.sum())

    @property
    def failures_by_status(self) -> dict[str, int]:
        """Failed problems so far by status name (only the codes that occurred)."""
        return {Status(c).name: int(n) for c, n in enumerate(self.counts) if n and is_failure(c)}

    @property
    def failures(self) -> int:
        """Failed problems so far (their impulses were zeros)."""
        return sum(self.failures_by_status.values())

    def reset(self) -> None:
        """Set the counters to zero."""
        self.calls = 0
        self.counts[:] = 0

"""The contact solver as the physics uses it: tolerances, the failure policy and counters, around one back end.

``ContactSolver()`` raises :class:`~diffcontact.errors.ContactSolverError` on a failed problem (the default: no
silent zero impulses); ``ContactSolver(on_failure="count")`` continues with zero impulses for the failed problems,
logs a warning and counts them by status (training, the simulation benchmark), and with ``keep`` > 0 keeps the first
failed problems as they were given, so that they can be saved (``save_failed``), loaded (``load_failed``) and solved
again.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from diffcontact.files import save_npz
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

    tol, acceptable_tol, max_iter: passed to the back end; on_failure: "raise" or "count" (see the module doc);
    keep: how many failed problems to keep in ``failed`` (0: none).
    Counters: ``calls`` (batches solved), ``counts`` (problems by :class:`Status`, all codes).
    """

    tol: float = POLICY.tol
    acceptable_tol: float = POLICY.acceptable_tol
    max_iter: int = POLICY.max_iter
    on_failure: Literal["raise", "count"] = "raise"
    backend: Callable = field(default=solve_cone_qp, repr=False)
    keep: int = 0
    calls: int = field(default=0, init=False)
    failed: list[dict[str, np.ndarray]] = field(default_factory=list, init=False, repr=False)
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
        flat_tol: float | None = None,
    ) -> torch.Tensor:
        """f (B, K·d) for a batch (A: (B, K·d, K·d), q: (B, K·d), mu, lower, active: (B, K)); see ``backend``
        (``flat_tol``, where given, is passed on to it)."""
        extra = {} if flat_tol is None else {"flat_tol": flat_tol}
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
            **extra,
        )
        self.calls += 1
        counts = np.bincount(info.status.numpy(), minlength=_N_STATUS)
        self.counts += counts
        if counts[_CONVERGED] < len(f):  # (all converged, the common case, needs no more: 3 µs of a small call)
            failed = counts * _FAILURE_CODES
            if np.count_nonzero(failed):
                names = {Status(c).name: int(n) for c, n in enumerate(failed) if n}
                log.warning("contact solver failed for %s of %d problems; their impulses are zero", names, len(f))
                if len(self.failed) < self.keep:
                    self._keep(A, q, mu, lower, active, info.status.numpy())
        return f

    def _keep(self, A, q, mu, lower, active, status: np.ndarray) -> None:
        """Keep the failed elements of this batch (as given: dtype and all) up to ``keep``, each with its position
        ``index`` and the whole batch (``batch_A`` …): an ill-conditioned element's outcome can depend on the batch
        around it (docs/solver.md, "Reproducible across batch positions")."""
        given = {"A": A, "q": q, "mu": mu} | ({"lower": lower} if lower is not None else {})
        given |= {"active": active} if active is not None else {}
        given = {k: v.detach().cpu().numpy() for k, v in given.items()}
        for b in np.flatnonzero(is_failure(status))[: self.keep - len(self.failed)].tolist():
            problem = {k: v[b] for k, v in given.items()} | {
                "status": np.asarray(status[b], np.int64),
                "index": np.asarray(b, np.int64),
            }
            self.failed.append(problem | {f"batch_{k}": v for k, v in given.items()})

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
        """Set the counters to zero and forget the kept problems."""
        self.calls = 0
        self.counts[:] = 0
        self.failed.clear()


def save_failed(path: str | Path, problems: list[dict[str, np.ndarray]]) -> Path:
    """Write failed problems (``ContactSolver.failed``) to ``path`` (.npz, atomically): for problem i the arrays
    ``i/A`` (n, n), ``i/q`` (n,), ``i/mu`` (K,), ``i/status`` (), ``i/index`` () and, where given, ``i/lower``,
    ``i/active`` (K,), and its batch ``i/batch_A`` (B, n, n) … (the element is row ``index`` of it)."""
    return save_npz(path, **{f"{i}/{k}": v for i, problem in enumerate(problems) for k, v in problem.items()})


def load_failed(path: str | Path) -> list[dict[str, np.ndarray]]:
    """The problems of a ``save_failed`` file, in order; each solves again with
    ``solve_cone_qp(*(torch.from_numpy(p[k])[None] for k in ("A", "q", "mu")), lower, active)``."""
    with np.load(path) as data:
        problems: dict[int, dict[str, np.ndarray]] = {}
        for key in data.files:
            i, name = key.split("/")
            problems.setdefault(int(i), {})[name] = data[key]
    return [problems[i] for i in sorted(problems)]

"""The per-element status codes, the failure rule and the weak-cone threshold.

Their one definition is ``csrc/api.h``; these are its Python copies, which ``kernel.py`` checks against the compiled
kernel when it loads it (an import error names any disagreement: a stale build).
"""

from __future__ import annotations

from enum import IntEnum

from diffcontact.solver.policy import POLICY


class Status(IntEnum):
    """Per-element solver status."""

    CONVERGED = 0  #: residuals below ``tol``
    INACCURATE = 1  #: iteration limit, residuals below ``acceptable_tol`` (usable, not an error)
    MAX_ITER = 2  #: iteration limit with large residuals (failure)
    NUMERICAL = 3  #: non-finite values or a failed factorisation (failure)
    UNBOUNDED = 4  #: the objective is unbounded below on the cones (failure)


#: The failure rule: an element whose status is at least this one has no usable solution (returned as zeros).
FIRST_FAILURE = Status.MAX_ITER

#: A ray or cone whose multiplier is at most WEAK_TOL·max(1, ‖slack‖) is weakly active (a contact exactly at a
#: stick/slip or touch/separate switch): polishing and the backward pass may take it as inactive.
WEAK_TOL = POLICY.weak_tol


_FIRST_FAILURE = int(FIRST_FAILURE)  # (numpy compares with an IntEnum member 20× slower than with an int)


def is_failure(status):
    """The failure rule on an array or tensor of status codes: True where the solution is not usable."""
    return status >= _FIRST_FAILURE

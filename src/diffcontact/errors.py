"""Exceptions raised by diffcontact. Each names what went wrong and what is allowed."""

from __future__ import annotations


class DiffContactError(Exception):
    """Base class of every error raised on purpose by diffcontact."""


class ConfigError(DiffContactError, ValueError):
    """A configuration value is missing or out of its allowed range (the message names the field)."""


class ContactSolverError(DiffContactError, RuntimeError):
    """The contact solver did not converge for some batch elements.

    Attributes:
        status: (B,) integer tensor of per-element status codes (see ``diffcontact.solver.Status``).
        failed: list of the failing batch indices.
    """

    def __init__(self, message: str, status=None, failed: list[int] | None = None):
        super().__init__(message)
        self.status = status
        self.failed = failed or []


class IndefiniteMatrixError(DiffContactError, ValueError):
    """The contact solver's A has an eigenvalue below −τ·max diag(A): not positive semidefinite, even up to
    rounding (``diffcontact.solver.least_norm``).  The message names the batch elements."""


class DatasetError(DiffContactError, RuntimeError):
    """A dataset file is missing, corrupt, or does not match its metadata or config."""

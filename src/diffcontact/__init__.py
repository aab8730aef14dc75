"""diffcontact: learn the dynamics of colliding rigid bodies with a differentiable contact model."""

from diffcontact.errors import ConfigError, ContactSolverError, DatasetError
from diffcontact.solver import SolverInfo, Status, solve_cone_qp

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "ContactSolverError",
    "DatasetError",
    "SolverInfo",
    "Status",
    "solve_cone_qp",
    "__version__",
]

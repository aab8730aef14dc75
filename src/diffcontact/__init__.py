"""diffcontact: learn the dynamics of colliding rigid bodies with a differentiable contact model."""

import warnings

from diffcontact.threads import quiet_waiting_env, spin_warning

if _spinning := spin_warning():  # (torch loaded first: too late for the setting below)
    warnings.warn(_spinning, RuntimeWarning, stacklevel=2)
quiet_waiting_env()  # before torch loads its OpenMP runtime, which reads these once (diffcontact.threads)

# ruff: noqa: E402 (the imports below must come after the call above)
from diffcontact.config import available_tasks, load_task
from diffcontact.contact.impulse import ContactModel
from diffcontact.errors import ConfigError, ContactSolverError, DatasetError, IndefiniteMatrixError
from diffcontact.simulator import Simulator, simulator_for
from diffcontact.solver import SolverInfo, Status, solve_cone_qp
from diffcontact.state import Inertia, Params, State
from diffcontact.systems.registry import BENCHMARK_TASKS, build_task

__version__ = "0.1.0"

__all__ = [
    "BENCHMARK_TASKS",
    "ConfigError",
    "ContactModel",
    "ContactSolverError",
    "IndefiniteMatrixError",
    "DatasetError",
    "Inertia",
    "Params",
    "Simulator",
    "SolverInfo",
    "State",
    "Status",
    "available_tasks",
    "build_task",
    "load_task",
    "simulator_for",
    "solve_cone_qp",
    "__version__",
]

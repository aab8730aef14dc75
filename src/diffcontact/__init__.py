"""diffcontact: learn the dynamics of colliding rigid bodies with a differentiable contact model."""

import warnings
from typing import TYPE_CHECKING

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

if TYPE_CHECKING:  # (what the lazy entry points below are, for type checkers and editors)
    from diffcontact.data.generate import generate_dataset
    from diffcontact.data.measured import import_tosses
    from diffcontact.eval.evaluate import evaluate_nominal, evaluate_run
    from diffcontact.models.model import build_model
    from diffcontact.solver.contact_solver import ContactSolver
    from diffcontact.train.run import train_run

# The workflow's entry points, imported when first used (they load Lightning, plotting and the data layer, which
# the solver and the simulator do not need): ``dc.generate_dataset(...)``, ``dc.train_run(...)`` and so on.
_LAZY = {
    "ContactSolver": "diffcontact.solver.contact_solver",
    "build_model": "diffcontact.models.model",
    "generate_dataset": "diffcontact.data.generate",
    "train_run": "diffcontact.train.run",
    "evaluate_run": "diffcontact.eval.evaluate",
    "evaluate_nominal": "diffcontact.eval.evaluate",
    "import_tosses": "diffcontact.data.measured",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'diffcontact' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)


__all__ = [
    "BENCHMARK_TASKS",
    "ConfigError",
    "ContactModel",
    "ContactSolver",
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
    "build_model",
    "build_task",
    "evaluate_nominal",
    "evaluate_run",
    "generate_dataset",
    "import_tosses",
    "load_task",
    "simulator_for",
    "solve_cone_qp",
    "train_run",
    "__version__",
]

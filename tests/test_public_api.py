"""The package's public surface: what ``import diffcontact`` offers, pinned, and what it does not load."""

from __future__ import annotations

import subprocess
import sys

import pytest

import diffcontact as dc

PUBLIC = {
    "BENCHMARK_TASKS", "ConfigError", "ContactModel", "ContactSolver", "ContactSolverError", "IndefiniteMatrixError",
    "DatasetError", "Inertia", "Params", "Simulator", "SolverInfo", "State", "Status", "available_tasks",
    "build_model", "build_task", "evaluate_nominal", "evaluate_run", "generate_dataset", "import_tosses", "load_task",
    "simulator_for", "solve_cone_qp", "train_run", "__version__",
}  # fmt: skip


def test_the_public_names_are_pinned_and_resolve():
    assert set(dc.__all__) == PUBLIC and len(dc.__all__) == len(PUBLIC)
    for name in PUBLIC:
        assert getattr(dc, name) is not None, name
    assert set(dir(dc)) == PUBLIC


@pytest.mark.slow
def test_importing_the_package_does_not_load_the_training_stack():
    code = "import sys, diffcontact; print(sorted(m for m in ('lightning', 'matplotlib') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"

"""Problems captured from the simulation benchmark that stall from the default interior-point starting point (a
margin of 0.1 inside the cones) and are solved by the retry from CVXOPT's (margin 1): a BD5 contact (K = 3, d = 2,
a lower bound of 1e-17) and a rope limit set (K = 19, d = 1, singular A).  They must converge and agree with
Clarabel."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from solver_oracle import TOL_OBJ, clarabel_solve, kkt_residual

from diffcontact.solver import Status, solve_cone_qp

CAPTURED = torch.load(Path(__file__).parent / "data" / "solver_captured.pt", weights_only=True)


@pytest.mark.parametrize("case", CAPTURED, ids=[c["source"] for c in CAPTURED])
def test_captured_simulation_problem(case):
    A, q, mu, lower, active = case["A"], case["q"], case["mu"], case["lower"], case["active"]
    f, info = solve_cone_qp(A, q, mu, lower, active, return_info=True)
    assert (info.status <= Status.INACCURATE).all(), info.status
    d = A.shape[-1] // mu.shape[-1]
    lo = torch.zeros_like(mu) if lower is None else lower
    An, qn, mun, ln, fb = A[0].numpy(), q[0].numpy(), mu[0].numpy(), lo[0].numpy(), f[0].numpy()
    f_ref, obj_ref = clarabel_solve(An, qn, mun, ln, d)
    obj = 0.5 * fb @ An @ fb + qn @ fb
    scale = max(1.0, np.abs(f_ref).max())
    assert abs(obj - obj_ref) <= TOL_OBJ * max(1.0, abs(obj_ref), np.abs(qn).max() * scale)
    assert np.abs(An @ (fb - f_ref)).max() <= 1e-6 * scale  # A may be singular: compare A·f
    assert kkt_residual(An, qn, mun, ln, fb, d) <= 1e-7

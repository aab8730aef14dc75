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


FACE_CASES = ["solver_face_compression.pt", "solver_face_sliding_restitution.pt"]


@pytest.mark.parametrize("name", FACE_CASES)
def test_box_face_problem_is_solved_to_the_least_norm_minimiser(name):
    """A cube sliding on one face: four corners on the table, A of rank 6 in 12 rows, a face of minimisers.  The
    method run to the tight tolerance stalls there at a residual far above the one its looser first pass reached;
    that answer must be kept (captured from ``diffcontact generate Cube`` and from training on real tosses)."""
    from solver_oracle import clarabel_min_norm

    case = torch.load(Path(__file__).parent / "data" / name, weights_only=True)
    f, info = solve_cone_qp(**case, return_info=True)
    assert (info.status <= Status.INACCURATE).all(), info
    A, q, mu = case["A"][0].numpy(), case["q"][0].numpy(), case["mu"][0].numpy()
    lo = np.zeros(len(mu)) if case["lower"] is None else case["lower"][0].numpy()
    fb = f[0].numpy()
    f_ref, obj_ref = clarabel_solve(A, q, mu, lo, 3)
    assert abs(0.5 * fb @ A @ fb + q @ fb - obj_ref) <= 1e-9 * max(1.0, abs(obj_ref))
    assert kkt_residual(A, q, mu, lo, fb, 3) <= 1e-7
    # every minimiser has f's range part (f is one, by its objective): Clarabel's least-norm point with that part
    least = clarabel_min_norm(A, q, mu, lo, 3, fb)
    assert np.linalg.norm(fb) <= np.linalg.norm(least) * (1 + 1e-8)
    assert np.abs(fb - least).max() <= 1e-6 * np.abs(least).max()
    # ... and with the range part of Clarabel's own minimiser (less accurate: its objective is up to 1e-10 higher)
    assert np.abs(fb - clarabel_min_norm(A, q, mu, lo, 3, f_ref)).max() <= 1e-4 * np.abs(least).max()

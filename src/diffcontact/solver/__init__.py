"""Batched, differentiable solver of the contact cone QPs (paper Eqs. 15 and 17).

``solve_cone_qp`` is the fast primal-dual interior-point back end with implicit differentiation;
``ContactSolver`` holds its options, the failure policy and counters (what the contact model calls);
``diffcontact.solver.reference.solve_cone_qp_reference`` is the cvxpylayers oracle (optional extra).
"""

from diffcontact.solver.contact_solver import ContactSolver
from diffcontact.solver.problem import SolverInfo, Status, solve_cone_qp

__all__ = ["ContactSolver", "SolverInfo", "Status", "solve_cone_qp"]

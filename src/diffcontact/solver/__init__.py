"""Batched, differentiable solver of the contact cone QPs (paper Eqs. 15 and 17).

``solve_cone_qp`` is the fast primal-dual interior-point back end with implicit differentiation;
``diffcontact.solver.reference.solve_cone_qp_reference`` is the cvxpylayers oracle (optional extra).
"""

from diffcontact.solver.problem import SolverInfo, Status, solve_cone_qp

__all__ = ["SolverInfo", "Status", "solve_cone_qp"]

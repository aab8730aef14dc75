"""The paper's three baselines (paper Sec. 5), with the interface of the contact models.

MLP-CD-CLNN (learned CLNN, known collision detection, an MLP velocity jump), IN-CP-CLNN (learned CLNN plus an
interaction network at every step) and IN-CP-SP (an interaction network alone).  They train on one-step pairs.
"""

from __future__ import annotations

import torch

from diffcontact.dynamics.lagrangian import potential_force
from diffcontact.dynamics.potentials import Gravity, SumPotential
from diffcontact.errors import ConfigError
from diffcontact.models.baselines.base import Baseline, point_inverse_inertia
from diffcontact.models.baselines.graphs import RelationGraph, relation_graph
from diffcontact.models.baselines.interaction import InteractionNetCLNN, InteractionNetSP, InteractionNetwork
from diffcontact.models.baselines.mlp_cd import MLPCollisionCLNN
from diffcontact.models.params import LearnedParams
from diffcontact.simulator import Simulator

BASELINE_NAMES = ("MLP-CD-CLNN", "IN-CP-CLNN", "IN-CP-SP")

__all__ = [
    "BASELINE_NAMES",
    "Baseline",
    "InteractionNetCLNN",
    "InteractionNetSP",
    "InteractionNetwork",
    "MLPCollisionCLNN",
    "RelationGraph",
    "build_baseline",
    "relation_graph",
]


def _gravity_force(task) -> torch.Tensor:
    """The true gravity force −∇V_g (P, d) in N: the task potential's Gravity terms (linear, so constant)."""
    pot = task.params.potential
    terms = [t for t in (pot.terms if isinstance(pot, SumPotential) else (pot,)) if isinstance(t, Gravity)]
    x = torch.zeros(1, task.system.n_points, task.system.d, dtype=torch.float64)
    return potential_force(task.params.replace(potential=SumPotential(*terms)), x)[0].detach()


def build_baseline(
    task, name: str, *, hidden: int = 256, layers: int = 3, seed: int = 0, moments_init: float = 1.0
) -> Baseline:
    """One of :data:`BASELINE_NAMES` for a Task, float64.  ``hidden``, ``layers``: the learned potential's MLP (and
    MLP-CD-CLNN's jump MLP; the paper's 256 × 3); the interaction networks have the published sizes.  The CLNN
    baselines learn the bodies' inertia as the contact models do: ``moments_init`` (m² per unit mass) is where the
    second moments start, and a box learns its centre of mass (``LearnedParams``)."""
    if name not in BASELINE_NAMES:
        raise ConfigError(f"model = {name!r} is not one of {list(BASELINE_NAMES)}")
    system = task.system
    gen = torch.Generator().manual_seed(seed)
    if name == "IN-CP-SP":
        graph = relation_graph(system)
        inv = point_inverse_inertia(task.params.inertia.masses, task.params.inertia.moments).to(torch.float64)
        rel = graph.relation_attributes(task.params.mu, task.params.e)
        return InteractionNetSP(graph, rel, inv, _gravity_force(task), system.d, task.dt, gen)
    params = LearnedParams(
        system.n_bodies,
        task.params.inertia.moments.shape[-1],
        system.n_points,
        system.d,
        0,  # no contact slots: μ and e are not learned
        homogeneous=False,
        hidden=hidden,
        layers=layers,
        seed=seed,
        moments_init=moments_init,
        com=task.params.inertia.com is not None,
    )
    sim = Simulator(system, "lagrangian")
    if name == "MLP-CD-CLNN":
        return MLPCollisionCLNN(sim, params, task.dt, hidden, layers, gen)
    graph = relation_graph(system)
    rel = graph.relation_attributes(task.params.mu, task.params.e)
    return InteractionNetCLNN(sim, params, graph, rel, task.dt, gen)

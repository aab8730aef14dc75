"""The interaction-network baselines (paper Sec. 5; Battaglia et al. 2016).

IN-CP-SP: the interaction network alone predicts each point's next velocity from the state, the true inverse
inertia and radii (object attributes), the true μ and e (relation attributes) and the true gravity (external
force); positions advance by explicit Euler with the old velocity, x' = x + v dt.
IN-CP-CLNN: one RK4 step of the learned CLNN (no collision detection), then the network adds Δv to the velocity,
given the learned inverse inertia, the true radii, μ and e, and the learned potential's force −∇V (the published
code passed +∇V).

One step, batched over samples and relations (static object weights, no loop):
    relation input   [o_recv − o_send (2d), a_recv (2), a_send (2), relation attributes (D_R)]
    effects          φ_R (hidden ReLU layers) -> effect size, summed per receiver
    object input     [x, v (2d), attributes (2), external force (d), summed effect]
    output           φ_O (one hidden ReLU layer) -> d per point
A relation that the graph lists more than once (the rope's two sides of a limit share their slot, so their inputs
are the same) goes through φ_R once and its effect counts as often as it is listed: the same sums, with half of φ_R's
work on the ropes.
"""

from __future__ import annotations

from typing import cast

import torch
from torch import nn

from diffcontact.dynamics.lagrangian import potential_force
from diffcontact.models.baselines.base import Baseline, mlp, point_inverse_inertia
from diffcontact.models.baselines.graphs import RelationGraph
from diffcontact.models.params import LearnedParams
from diffcontact.simulator import Simulator

N_OBJECT_ATTRIBUTES = 2  # inverse inertia, contact radius
SIZES = {  # (relational hidden, relational layers, effect, object hidden), the published sizes
    "IN-CP-CLNN": (150, 4, 50, 100),
    "IN-CP-SP": (300, 4, 50, 200),
}


class InteractionNetwork(nn.Module):
    """φ_R and φ_O over a fixed :class:`RelationGraph` (its weights and relation attributes held as buffers)."""

    recv: torch.Tensor  # (the buffers registered in __init__)
    send: torch.Tensor
    static: torch.Tensor
    radius: torch.Tensor
    rel_attr: torch.Tensor
    recv_distinct: torch.Tensor
    send_distinct: torch.Tensor
    rel_attr_distinct: torch.Tensor
    effect_weights: torch.Tensor

    def __init__(self, graph: RelationGraph, rel_attr: torch.Tensor, d: int, sizes: tuple, generator):
        super().__init__()
        rel_hidden, rel_layers, effect, obj_hidden = sizes
        self.P, self.d = graph.n_points, d
        self.register_buffer("recv", graph.recv.clone())
        self.register_buffer("send", graph.send.clone())
        self.register_buffer("static", graph.static.clone())
        self.register_buffer("radius", graph.radius.clone())
        self.register_buffer("rel_attr", rel_attr.clone())
        # (derived from the buffers above, not saved: the distinct relations and each one's summed receiver weights)
        distinct, counted = _distinct_relations(torch.cat([graph.recv, graph.send, rel_attr.to(graph.recv)], 1))
        self.register_buffer("recv_distinct", graph.recv[distinct].clone(), persistent=False)
        self.register_buffer("send_distinct", graph.send[distinct].clone(), persistent=False)
        self.register_buffer("rel_attr_distinct", rel_attr[distinct].clone(), persistent=False)
        self.register_buffer("effect_weights", (counted @ graph.recv[:, : self.P]).clone(), persistent=False)
        n_rel_in = 2 * d + 2 * N_OBJECT_ATTRIBUTES + rel_attr.shape[-1]
        n_obj_in = 2 * d + N_OBJECT_ATTRIBUTES + d + effect
        self.relational = mlp([n_rel_in] + [rel_hidden] * rel_layers + [effect], generator).to(torch.float64)
        self.object = mlp([n_obj_in, obj_hidden, d], generator).to(torch.float64)

    @property
    def input_sizes(self) -> tuple[int, int]:
        """(relation input, object input) widths."""
        # (the first layers are nn.Linear: ``mlp``; torch types an indexed Sequential as any Module)
        return cast(nn.Linear, self.relational[0]).in_features, cast(nn.Linear, self.object[0]).in_features

    def forward(self, x: torch.Tensor, v: torch.Tensor, inv_inertia: torch.Tensor, force: torch.Tensor) -> torch.Tensor:
        """Per-point output (B, P, d) from x, v (B, P, d), inverse inertia (P,) and external force (B, P, d)."""
        obj, attr = self.objects(x, v, inv_inertia)
        effects = self.effects(
            obj, attr, self.recv_distinct, self.send_distinct, self.rel_attr_distinct, self.effect_weights
        )
        inp = torch.cat([obj[:, : self.P], attr[: self.P].expand(x.shape[0], -1, -1), force, effects], -1)
        return self.object(inp)

    def objects(self, x: torch.Tensor, v: torch.Tensor, inv_inertia: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Every object's state (B, N_O, 2d), the static ones at rest, and attributes (N_O, 2): inverse inertia
        (0 for static objects) and contact radius."""
        B, S = x.shape[0], self.static.shape[0]
        obj = torch.cat(
            [torch.cat([x, self.static.expand(B, S, self.d)], 1), torch.cat([v, v.new_zeros(B, S, self.d)], 1)], -1
        )
        attr = torch.stack([torch.cat([inv_inertia.to(x), x.new_zeros(S)]), self.radius], -1)
        return obj, attr

    def effects(self, obj, attr, recv, send, rel_attr, weights) -> torch.Tensor:
        """φ_R of relations with receiver and sender weights ``recv``, ``send`` (R, N_O) and attributes
        ``rel_attr`` (R, D_R), summed into each point with ``weights`` (R, P): (B, P, effect)."""
        B = obj.shape[0]
        rel = torch.cat(
            [
                torch.einsum("ro,bof->brf", recv - send, obj),
                (recv @ attr).expand(B, -1, -1),
                (send @ attr).expand(B, -1, -1),
                rel_attr.expand(B, -1, -1),
            ],
            -1,
        )
        return torch.einsum("ro,bre->boe", weights, self.relational(rel))


def _distinct_relations(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The first of each set of equal ``rows`` (N_R, D), in the order of the rows, (N_U,); and (N_U, N_R), 1 where
    relation r is a copy of distinct relation u."""
    _, inverse = torch.unique(rows, dim=0, return_inverse=True)
    first = torch.full((int(inverse.max()) + 1,), rows.shape[0], dtype=torch.long)
    first = first.scatter_reduce(0, inverse, torch.arange(rows.shape[0]), "amin")
    order = torch.argsort(first)  # (distinct relations in the order the graph lists them first)
    counted = (inverse[None, :] == order[:, None]).to(rows)
    return first[order], counted


class InteractionNetSP(Baseline):
    """IN-CP-SP: v' = IN(x, v), x' = x + v dt, given the true inverse inertia (P,), gravity force (P, d)."""

    inv_inertia: torch.Tensor  # (the buffers registered in __init__)
    gravity: torch.Tensor

    def __init__(self, graph: RelationGraph, rel_attr, inv_inertia, gravity_force, d: int, dt: float, generator):
        super().__init__()
        self.name, self.dt, self.params = "IN-CP-SP", dt, None
        self.net = InteractionNetwork(graph, rel_attr, d, SIZES["IN-CP-SP"], generator)
        self.register_buffer("inv_inertia", inv_inertia.clone())
        self.register_buffer("gravity", gravity_force.clone())

    def step(self, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        force = self.gravity.expand_as(x)
        return x + v * self.dt, self.net(x, v, self.inv_inertia, force)


class InteractionNetCLNN(Baseline):
    """IN-CP-CLNN: (x', v_c) = learned CLNN step; v' = v_c + IN(x', v_c) with the learned inertia and −∇V(x')."""

    def __init__(
        self, simulator: Simulator, params: LearnedParams, graph: RelationGraph, rel_attr, dt: float, generator
    ):
        super().__init__()
        self.name, self.simulator, self.params, self.dt = "IN-CP-CLNN", simulator, params, dt
        self.net = InteractionNetwork(graph, rel_attr, simulator.system.d, SIZES["IN-CP-CLNN"], generator)

    def step(self, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self.params is None:
            raise TypeError(f"{self.name} has no learned CLNN parameters")
        p = self.params()
        x1, v1 = self.simulator.flow(p, x, v, self.dt)
        inv = point_inverse_inertia(p.inertia.masses, p.inertia.moments)
        return x1, v1 + self.net(x1, v1, inv, potential_force(p, x1))

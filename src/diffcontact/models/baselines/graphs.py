"""Relation graphs of the interaction-network baselines, built from a System's declared structure.

Objects are the System's points, then the static objects that some relation uses: the fixed anchors (pendulum
pivot, rope anchor) and one object per wall or plane, at the projection of the centre of the System's view box
onto it (the box's wall midpoints, the pendulum's ground point below the pivot, the gyroscope's wall point
(0, −0.33, 0)).  Static objects have zero velocity and are never updated.

Relations (receiver ← sender), with weights over objects so that a "soft" object (a mean of points) can take part:
- distance constraints: both directions (equality relations);
- sphere pairs: between the bodies' first points, both directions;
- spheres or disk rims against a plane: the body's first point ← the plane's object;
- a box's corners against a plane: the body's first point ← the plane's object, once per body and plane;
- stretch limits of a link a→b: both directions, one per limit side;
- bend limits at b between links a→b→c: b ← mean(a, c) and mean(a, c) ← b, one per limit side.
A relation whose receiver lies wholly on static objects is left out (its effect would be discarded).  Relation
attributes are the true (μ, e) of the contact's slot (0, 0 for equality relations), plus a ±1 column (contact /
equality) when the graph has equality relations.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from diffcontact.contact.kinds import (
    AngleLimits,
    DiskRimPlanes,
    SpherePairs,
    SpherePlanes,
    StretchLimits,
    VertexPlanes,
)
from diffcontact.systems.base import System

F64 = torch.float64
EQUALITY = -1  # slot of an equality relation


@dataclass(frozen=True)
class RelationGraph:
    """n_points dynamic objects, then static objects at ``static`` (S, d); ``radius`` (N_O,) contact radius per
    object (0 where none); ``recv``, ``send`` (N_R, N_O) object weights of each relation; ``slot`` (N_R,) contact
    slot into μ, e or ``EQUALITY``."""

    n_points: int
    static: torch.Tensor
    radius: torch.Tensor
    recv: torch.Tensor
    send: torch.Tensor
    slot: torch.Tensor

    @property
    def n_objects(self) -> int:
        return self.recv.shape[1]

    @property
    def n_relations(self) -> int:
        return self.recv.shape[0]

    @property
    def has_equality(self) -> bool:
        return bool((self.slot == EQUALITY).any())

    def relation_attributes(self, mu: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
        """(N_R, D_R): (μ, e) of each relation's slot (0 for equality relations)[, +1 contact / −1 equality]."""
        eq = self.slot == EQUALITY
        idx = self.slot.clamp_min(0)
        cols = [torch.where(eq, 0.0, mu.to(F64)[idx]), torch.where(eq, 0.0, e.to(F64)[idx])]
        if self.has_equality:
            cols.append(torch.where(eq, -1.0, 1.0).to(F64))
        return torch.stack(cols, dim=-1)


def _view_centre(system: System) -> torch.Tensor:
    return torch.tensor([0.5 * (lo + hi) for lo, hi in system.drawing.view], dtype=F64)


def relation_graph(system: System) -> RelationGraph:
    """The relation graph of ``system`` (see the module docstring).  Built once; a loop over declared
    candidates at build time only."""
    P, d = system.n_points, system.d
    anchors = system.anchors.to(F64)
    centre = _view_centre(system)
    planes: list[tuple[tuple[float, ...], torch.Tensor]] = []  # (key, position)
    radius = torch.zeros(P, dtype=F64)
    rels: list[tuple[dict[int, float], dict[int, float], int]] = []

    def plane_object(n: torch.Tensor, c: torch.Tensor) -> int:
        key = tuple(round(float(a), 12) for a in (*n.tolist(), float(c)))
        for k, (other, _) in enumerate(planes):
            if other == key:
                return P + anchors.shape[0] + k
        planes.append((key, centre - ((centre @ n.to(F64)) + c.to(F64)) * n.to(F64)))
        return P + anchors.shape[0] + len(planes) - 1

    def both(a: dict[int, float], b: dict[int, float], slot: int) -> None:
        rels.extend([(a, b, slot), (b, a, slot)])

    for i, j in zip(system.constraints.dist_i.tolist(), system.constraints.dist_j.tolist()):
        both({i: 1.0}, {j: 1.0}, EQUALITY)
    for kind in system.detector.kinds:
        slots = kind.slot.tolist()
        if isinstance(kind, SpherePairs):
            radius[kind.pts_i] = kind.ri.to(F64)[:, None].expand_as(kind.pts_i).clone()
            radius[kind.pts_j] = kind.rj.to(F64)[:, None].expand_as(kind.pts_j).clone()
            for a, b, s in zip(kind.pts_i[:, 0].tolist(), kind.pts_j[:, 0].tolist(), slots):
                both({a: 1.0}, {b: 1.0}, s)
        elif isinstance(kind, (SpherePlanes, DiskRimPlanes)):
            r = kind.r if isinstance(kind, SpherePlanes) else kind.R
            radius[kind.pts] = r.to(F64)[:, None].expand_as(kind.pts).clone()
            for k, s in enumerate(slots):
                rels.append(({int(kind.pts[k, 0]): 1.0}, {plane_object(kind.n[k], kind.c[k]): 1.0}, s))
        elif isinstance(kind, VertexPlanes):  # (one relation per body and plane, its reach the farthest corner)
            corner = (kind.weights[:, 1:] ** 2).sum(-1).sqrt().to(F64)  # (K,) |b| of each corner, m
            seen: set[tuple[int, int]] = set()
            for k, s in enumerate(slots):
                body, plane = int(kind.pts[k, 0]), plane_object(kind.n[k], kind.c[k])
                radius[body] = max(float(radius[body]), float(corner[k]))
                if (body, plane) not in seen:
                    seen.add((body, plane))
                    rels.append(({body: 1.0}, {plane: 1.0}, s))
        elif isinstance(kind, StretchLimits):
            for a, b, s in zip(kind.a.tolist(), kind.b.tolist(), slots):
                both({b: 1.0}, {a: 1.0}, s)
        elif isinstance(kind, AngleLimits):
            for a, b, c, s in zip(kind.a.tolist(), kind.b.tolist(), kind.cc.tolist(), slots):
                both({b: 1.0}, {a: 0.5, c: 0.5}, s)
        else:
            raise TypeError(f"no interaction-network relations declared for contact kind {type(kind).__name__}")
    rels = [r for r in rels if any(o < P for o in r[0])]  # (a receiver wholly static gets discarded effects)
    n_all = P + anchors.shape[0] + len(planes)
    used = sorted({o for r in rels for part in r[:2] for o in part} | set(range(P)))
    new = {o: k for k, o in enumerate(used)}
    positions = torch.cat([anchors, torch.stack([p for _, p in planes]) if planes else anchors[:0]])  # (n_all − P, d)
    recv = torch.zeros(len(rels), len(used), dtype=F64)
    send = torch.zeros_like(recv)
    for k, (r, s, _) in enumerate(rels):
        for o, w in r.items():
            recv[k, new[o]] += w
        for o, w in s.items():
            send[k, new[o]] += w
    static = positions[[o - P for o in used if o >= P]] if n_all > P else torch.zeros(0, d, dtype=F64)
    full_radius = torch.cat([radius, torch.zeros(len(used) - P, dtype=F64)])
    return RelationGraph(P, static.reshape(-1, d), full_radius, recv, send, torch.tensor([s for *_, s in rels]))

"""System (static structure and geometry) and Task (a system with its true Params and sampler)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar, Protocol

import torch

from diffcontact.config import TaskConfig
from diffcontact.contact.detect import Detector
from diffcontact.dynamics.constraints import Constraints
from diffcontact.dynamics.inertia import kinetic_energy
from diffcontact.state import Params, State, with_anchors


@dataclass(frozen=True)
class Drawing:
    """What a renderer needs: body radii (n_bodies,), segments (S, 2) of extended point indices to draw as
    links, planes as (normal (W, d), offset (W,)), the body shape ("ball", "disk2d", "disk3d") and a view
    box ((lo, hi) per axis)."""

    radii: torch.Tensor
    segments: torch.Tensor
    plane_normal: torch.Tensor
    plane_offset: torch.Tensor
    shape: str
    view: tuple[tuple[float, float], ...]


@dataclass(frozen=True)
class Stepping:
    """How a frame of length dt is integrated: ``substeps`` RK4 steps of dt/substeps, each followed by the
    contacts; with ``time_of_impact`` contacts are resolved at their time of impact (contact/toi.py), else at
    the end of each substep (the published scheme). From ``task.substeps`` and ``contact.time_of_impact``."""

    time_of_impact: bool = False
    substeps: int = 1


class NoiseCoordinates(Protocol):
    """Coordinates of a System in which observation noise is drawn i.i.d. (``data/noise.py``), e.g. the chain
    pendulum's link angles: ``name`` (recorded in the dataset), ``from_cartesian(x, v) -> (q, w)`` and
    ``to_cartesian(q, w) -> (x, v)`` (x, v: (B, P, d); q, w: (B, k)), inverse maps on the constraint manifold;
    ``size``: k."""

    name: ClassVar[str]

    @property
    def size(self) -> int: ...

    def from_cartesian(self, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]: ...

    def to_cartesian(self, q: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]: ...


@dataclass(frozen=True, eq=False)
class Links:
    """Pairs of points joined by a link of known rest length (the rope's segments): ``i``, ``j`` (L,) extended
    point indices (>= P: the rows of ``anchors`` (n_anchors, d)), ``rest`` (L,) the rest lengths in m and
    ``spread`` (L,) the stretch in m that a learned link potential takes as its unit (the stretch limit's)."""

    i: torch.Tensor
    j: torch.Tensor
    rest: torch.Tensor
    spread: torch.Tensor
    anchors: torch.Tensor

    def stretch(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """s = (|x_i − x_j| − rest) / spread (B, L) and the unit vectors (x_i − x_j) / |x_i − x_j| (B, L, d):
        x (B, P, d) in m."""
        ext = with_anchors(x, self.anchors)
        delta = ext[:, self.i] - ext[:, self.j]
        length = delta.norm(dim=-1)
        return (length - self.rest.to(x)) / self.spread.to(x), delta / length[..., None]


@dataclass(eq=False)
class System:
    """Static structure of a rigid-body system in Cartesian coordinates.

    d: spatial dimension; n_bodies bodies of ``points_per_body`` points each (1 for point masses, d + 1 for
    extended bodies), P = n_bodies · points_per_body points, D = P d coordinates; ``anchors`` (n_anchors, d)
    are fixed world points addressed by extended point indices P, P + 1, ...; ``constraints`` are the
    holonomic constraints; ``detector`` holds every contact candidate; ``n_slots`` is the length of μ and e;
    ``stepping`` is the task's default time-stepping scheme (the Simulator may override it);
    ``noise_coordinates``: the coordinates observation noise is drawn in (None: Cartesian, projected back onto the
    constraints if there are any); ``links``: pairs of points joined by a link of known rest length (None: none).
    """

    name: str
    d: int
    n_bodies: int
    points_per_body: int
    anchors: torch.Tensor
    constraints: Constraints
    detector: Detector
    n_slots: int
    drawing: Drawing
    stepping: Stepping = Stepping()
    noise_coordinates: NoiseCoordinates | None = None
    links: Links | None = None

    @property
    def n_points(self) -> int:
        return self.n_bodies * self.points_per_body

    def energy(self, params: Params, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Total energy ½vᵀMv + V(x): x, v (B, P, d) -> (B,) in J."""
        return kinetic_energy(params.inertia, v) + params.potential_energy(x)


Sampler = Callable[[int, torch.Generator, torch.dtype], State]


@dataclass(eq=False)
class Task:
    """A benchmark task: its config, System, true Params and initial-condition sampler."""

    config: TaskConfig
    system: System
    params: Params
    sampler: Sampler = field(repr=False)

    @property
    def dt(self) -> float:
        return self.config.dt

    @property
    def frames(self) -> int:
        return self.config.frames

    @property
    def dtype(self) -> torch.dtype:
        return getattr(torch, self.config.dtype)

    def sample(self, n: int, seed: int) -> State:
        """n initial states (not in contact), reproducible from ``seed`` (a torch.Generator on CPU)."""
        gen = torch.Generator().manual_seed(seed)
        return self.sampler(n, gen, self.dtype)

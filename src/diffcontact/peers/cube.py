"""What the two engine peers share: the nominal cube, the fitted parameters' bounds, and rolling tosses out in groups.

The cube is the ContactNets one at its nominal values (Pfrommer et al., CoRL 2020, ``experiment.json``): half-extent
0.0524 m, mass 0.37 kg, isotropic inertia 0.00081 kg m², gravity 9.81 m/s² along −z of the table frame. Its centre of
mass may sit off the box's centre (``COM_PARAMETERS``, optional in every engine: 0 when absent); the box stays where
it is, and the mass and the inertia are about the centre of mass. The poses in and out are the box centre's.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from diffcontact.data.measured import GRAVITY  # noqa: F401 (m/s²: the first states' fit and the cubes use one g)
from diffcontact.data.tosses import CONTACTNETS_LENGTH_SCALE, Tosses
from diffcontact.errors import ConfigError

HALF_EXTENT = CONTACTNETS_LENGTH_SCALE  # m
MASS = 0.37  # kg
INERTIA = 0.00081  # kg m², each principal moment
NOMINAL_FRICTION = 0.18  # the ContactNets experiment's μ
NOMINAL_RESTITUTION = 0.125  # the ContactNets experiment's e
SUBSTEPS = 10  # engine steps per recorded frame (dt / 10, as Acosta et al. for Bullet; the same for MuJoCo)
GROUP_SIZE = 64  # tosses rolled out together, sorted by length (the shorter ones idle to the group's longest)


@dataclass(frozen=True)
class Param:
    """One fitted parameter: bounds [low, high] (its unit in ``unit``), searched on a log scale if ``log``;
    ``nominal`` is the unfitted value (None: the engine's default contact, which this parameter does not describe)."""

    name: str
    low: float
    high: float
    log: bool
    nominal: float | None
    unit: str = ""

    def value(self, u: float) -> float:
        """The value at the fraction u in [0, 1] of the (log) range."""
        u = min(max(float(u), 0.0), 1.0)
        if self.log:
            return float(self.low * (self.high / self.low) ** u)
        return float(self.low + u * (self.high - self.low))

    def fraction(self, value: float) -> float:
        """Inverse of ``value``: where ``value`` lies in the (log) range, in [0, 1]."""
        if self.log:
            u = math.log(value / self.low) / math.log(self.high / self.low)
        else:
            u = (value - self.low) / (self.high - self.low)
        return min(max(u, 0.0), 1.0)

    def start(self) -> float:
        """The search's starting fraction: the nominal value, or the middle of the range without one."""
        return 0.5 if self.nominal is None else self.fraction(self.nominal)


# the centre of mass's offset from the box's centre, in the body frame: com_x, com_y, com_z
COM_PARAMETERS = tuple(Param(f"com_{axis}", -0.02, 0.02, log=False, nominal=0.0, unit="m") for axis in "xyz")
COM_NAMES = tuple(p.name for p in COM_PARAMETERS)


def com_offset(params: dict[str, float]) -> np.ndarray:
    """The centre of mass (3,) in m, body frame, from the box's centre: ``params``' com_x, com_y, com_z (each 0
    if absent)."""
    return np.array([float(params.get(name, 0.0)) for name in COM_NAMES])


def nominal(params: tuple[Param, ...]) -> dict[str, float]:
    """The unfitted parameters (those with a nominal value)."""
    return {p.name: p.nominal for p in params if p.nominal is not None}


def check_params(
    given: dict[str, float], params: tuple[Param, ...], engine: str, optional: tuple[str, ...] = ()
) -> None:
    """ConfigError naming the field for a missing parameter (unless ``optional``), an unknown one or a value outside
    its bounds."""
    known = {p.name: p for p in params}
    missing = [name for name in known if name not in given and name not in optional]
    if missing:
        raise ConfigError(f"{engine}: parameters {missing} are missing")
    for name, value in given.items():
        if name not in known:
            raise ConfigError(f"{engine}: unknown parameter {name!r} (known: {', '.join(known)})")
        p = known[name]
        if not (math.isfinite(value) and p.low <= value <= p.high):
            raise ConfigError(f"{engine}: {name} = {value} is not in [{p.low:g}, {p.high:g}]")


def length_groups(lengths: np.ndarray, size: int = GROUP_SIZE) -> list[np.ndarray]:
    """Toss positions (n,) sorted by length, in chunks of at most ``size``: each chunk is rolled out to its
    longest toss, so sorting keeps the idle frames few."""
    order = np.argsort(lengths, kind="stable")
    return [order[i : i + size] for i in range(0, len(order), size)]


GroupRollout = Callable[[np.ndarray, int], tuple[np.ndarray, np.ndarray]]


def roll_out_groups(tosses: Tosses, run_group: GroupRollout) -> tuple[np.ndarray, np.ndarray]:
    """Predicted poses of every toss, as flat frame arrays like ``tosses``: position (F, 3) m and quaternion (F, 4)
    w, x, y, z. ``run_group(index (g,), frames)`` rolls the tosses ``index`` out from their first recorded frame
    and returns (g, frames, 3) and (g, frames, 4). Frame 0 of each toss is its recorded pose (the initial state)."""
    position = np.empty_like(tosses.position)
    quaternion = np.empty_like(tosses.quaternion)
    for group in length_groups(tosses.lengths):
        p, q = run_group(group, int(tosses.lengths[group].max()))
        for j, i in enumerate(group):
            rows = tosses.frames_of(int(i))
            n = rows.stop - rows.start
            position[rows], quaternion[rows] = p[j, :n], q[j, :n]
            position[rows.start], quaternion[rows.start] = tosses.position[rows.start], tosses.quaternion[rows.start]
    return position, quaternion

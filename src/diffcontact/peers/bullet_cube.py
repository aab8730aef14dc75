"""The cube on a table in Bullet (pybullet, DIRECT mode): a rigid body (maximal coordinates) on a static plane.

10 steps of dt / 10 a recorded frame, as Acosta et al.; pybullet's defaults otherwise (sequential impulses, 50
iterations, split impulse, restitution only above a normal speed of 0.2 m/s), linear and angular damping 0 and
sleeping disabled. A group of tosses shares one world: the cubes stand 1 m apart on a grid (a shift along the
plane, taken off again) and collide with the table only.

Bullet combines two bodies' values as: friction and restitution the product, stiffness in series, damping the sum.
The table gets friction 1 and restitution 1, and each body half the damping and twice the stiffness, so that the
contact has exactly the fitted values. Without ``contact_stiffness`` and ``contact_damping`` (the nominal model)
the contact is Bullet's default rigid one (ERP / CFM). Angular velocity is set in the table frame (ω body → R ω).

The centre of mass c (com_x, com_y, com_z, body frame, 0 when absent) is the base's inertial frame
(``baseInertialFramePosition``; mass and inertia about it), the box centred on the base's link frame. Bullet's base
state is the inertial frame's: ``resetBaseVelocity`` sets the centre of mass's velocity, and
``getBasePositionAndOrientation`` gives its position (``createMultiBody``'s ``basePosition`` is the link frame's). So a
cube starts from v_centre + R (ω × c) and its box centre is read back as p − R c. (Checked numerically, pybullet
3.2.7, maximal coordinates: at creation the read position is basePosition + R c; spinning without gravity, it moves
at the set velocity on a straight line while the box's AABB centre stays at it − R c, to 1e-15 m, also after a
reset.) With c = 0 the arithmetic adds exact zeros: the rollouts are the same to the bit.
"""

from __future__ import annotations

import numpy as np
import pybullet as pb  # pyright: ignore[reportMissingImports]  (an optional extra, absent where it is not installed)

from diffcontact.data.tosses import Tosses
from diffcontact.errors import ConfigError
from diffcontact.peers.cube import (
    COM_NAMES,
    COM_PARAMETERS,
    GRAVITY,
    HALF_EXTENT,
    INERTIA,
    MASS,
    NOMINAL_FRICTION,
    NOMINAL_RESTITUTION,
    SUBSTEPS,
    Param,
    check_params,
    com_offset,
    roll_out_groups,
)
from diffcontact.systems.poses import rotate

ENGINE = "bullet"
PARAMETERS = (
    Param("friction", 0.01, 1.0, log=True, nominal=NOMINAL_FRICTION),
    Param("restitution", 0.0, 0.95, log=False, nominal=NOMINAL_RESTITUTION),
    Param("contact_stiffness", 1e2, 1e8, log=True, nominal=None, unit="N/m"),
    Param("contact_damping", 1e-1, 1e5, log=True, nominal=None, unit="N s/m"),
)
COMPLIANT = ("contact_stiffness", "contact_damping")
SPACING = 1.0  # m between the cubes of one world
TABLE, CUBE = 1, 2  # collision groups


def _world(dt: float, table_height: float, params: dict[str, float]) -> int:
    """A new DIRECT world with the table; returns the client id."""
    c = pb.connect(pb.DIRECT)
    pb.setGravity(0.0, 0.0, -GRAVITY, physicsClientId=c)
    pb.setTimeStep(dt / SUBSTEPS, physicsClientId=c)
    shape = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=c)
    table = pb.createMultiBody(0.0, shape, basePosition=[0.0, 0.0, table_height], physicsClientId=c)
    pb.changeDynamics(table, -1, lateralFriction=1.0, restitution=1.0, **_compliance(params), physicsClientId=c)
    pb.setCollisionFilterGroupMask(table, -1, TABLE, CUBE, physicsClientId=c)
    return c


def _compliance(params: dict[str, float]) -> dict[str, float]:
    """Each body's share of the contact's stiffness and damping (none: Bullet's rigid contact)."""
    if "contact_stiffness" not in params:
        return {}
    return {"contactStiffness": 2.0 * params["contact_stiffness"], "contactDamping": 0.5 * params["contact_damping"]}


def simulate(tosses: Tosses, params: dict[str, float], table_height: float) -> tuple[np.ndarray, np.ndarray]:
    """Each toss rolled out from its first recorded frame for its length: position (F, 3) m, quaternion (F, 4)
    w, x, y, z, one row per recorded frame (frame 0 the recorded one). params: friction and restitution, and
    contact_stiffness (N/m) with contact_damping (N s/m) or neither, and the names of ``cube.COM_PARAMETERS`` (m),
    each 0 when absent; table_height: the table plane's z in m."""
    check_params(params, PARAMETERS + COM_PARAMETERS, ENGINE, optional=COMPLIANT + COM_NAMES)
    if sum(name in params for name in COMPLIANT) == 1:
        raise ConfigError(f"{ENGINE}: give {' and '.join(COMPLIANT)} together, or neither (rigid contact)")
    start = tosses.offsets[:-1]
    com = com_offset(params)
    omega_world = rotate(tosses.quaternion[start], tosses.omega[start][:, None])[:, 0]  # (n, 3): each toss's own
    com_world = rotate(tosses.quaternion[start], com[None])[:, 0]  # (n, 3): R c at each toss's first frame
    com_velocity = tosses.velocity[start] + np.cross(omega_world, com_world)  # v_centre + R (ω × c)

    def run_group(index: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray]:
        side, cell = int(np.ceil(np.sqrt(len(index)))), np.arange(len(index))
        shift = np.stack([cell % side, cell // side, np.zeros_like(cell)], 1) * SPACING
        c = _world(tosses.dt, table_height, params)
        try:
            box = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[HALF_EXTENT] * 3, physicsClientId=c)
            bodies = []
            for j, i in enumerate(index):
                f = int(start[i])
                w, x, y, z = tosses.quaternion[f]
                b = pb.createMultiBody(
                    MASS, box, basePosition=tosses.position[f] + shift[j], baseOrientation=[x, y, z, w],
                    baseInertialFramePosition=com, useMaximalCoordinates=True, physicsClientId=c,
                )  # fmt: skip
                pb.changeDynamics(
                    b, -1, mass=MASS, localInertiaDiagonal=[INERTIA] * 3, lateralFriction=params["friction"],
                    restitution=params["restitution"], linearDamping=0.0, angularDamping=0.0,
                    activationState=pb.ACTIVATION_STATE_DISABLE_SLEEPING, **_compliance(params), physicsClientId=c,
                )  # fmt: skip
                pb.resetBaseVelocity(b, com_velocity[i], omega_world[i], physicsClientId=c)
                pb.setCollisionFilterGroupMask(b, -1, CUBE, TABLE, physicsClientId=c)
                bodies.append(b)
            position = np.empty((len(index), frames, 3))
            quaternion = np.empty((len(index), frames, 4))
            for k in range(frames):
                for _ in range(SUBSTEPS if k else 0):
                    pb.stepSimulation(physicsClientId=c)
                for j, b in enumerate(bodies):
                    p, (x, y, z, w) = pb.getBasePositionAndOrientation(b, physicsClientId=c)
                    position[j, k], quaternion[j, k] = p, (w, x, y, z)
        finally:
            pb.disconnect(c)
        centre = position - rotate(quaternion.reshape(-1, 4), com[None]).reshape(position.shape)  # p − R c
        return centre - shift[:, None], quaternion

    return roll_out_groups(tosses, run_group)

"""The cube on a table in MuJoCo: one free body, one plane, rolled out with ``mujoco.rollout``.

Timestep dt / 10 (10 steps a recorded frame); MuJoCo's defaults otherwise (semi-implicit Euler, pyramidal friction
cones, Newton solver). The contact parameters are set on both geoms alike, so MuJoCo's mixing of two geoms' values
(friction: the larger; solref, solimp: averaged) returns them unchanged. solimp's midpoint and power keep their
defaults (0.5, 2); torsional and rolling friction theirs (0.005, 0.0001).

The body's frame is the box's: its origin the box centre, the centre of mass offset from it (com_x, com_y, com_z,
0 when absent) as the body's inertial frame (``<inertial pos>``; mass and inertia about it). The free joint's state
is that of the body frame's origin whatever the inertial frame: qpos = (box centre in the table frame, quaternion w,
x, y, z) and qvel = (box centre velocity in the table frame, angular velocity in the BODY frame), so the tosses'
states go in and the poses come out as they are. (Checked numerically, MuJoCo 4.0: with an offset c, data.xpos is
qpos[0:3] and data.xipos is xpos + R c; mj_objectVelocity gives qvel[0:3] for the body frame and qvel[0:3] + (R ω) ×
(R c) for the inertial frame.)
"""

from __future__ import annotations

from typing import cast

import numpy as np

# (MuJoCo is an optional extra, and its API lives in compiled modules without type stubs, so a type checker may
# not find the module, or not see these names)
from mujoco import MjData, MjModel, mj_getState, mj_resetData, mj_stateSize, mjtState, rollout  # pyright: ignore[reportAttributeAccessIssue, reportMissingImports]

from diffcontact.data.tosses import Tosses
from diffcontact.peers.cube import (
    COM_NAMES,
    COM_PARAMETERS,
    GRAVITY,
    HALF_EXTENT,
    INERTIA,
    MASS,
    NOMINAL_FRICTION,
    SUBSTEPS,
    Param,
    check_params,
    com_offset,
    roll_out_groups,
)

ENGINE = "mujoco"
MIN_TIMECONST = 2.0 * (1.0 / 148.0) / SUBSTEPS  # s: MuJoCo raises a smaller timeconst to 2 timesteps itself
PARAMETERS = (
    Param("friction", 0.01, 1.0, log=True, nominal=NOMINAL_FRICTION),
    Param("timeconst", MIN_TIMECONST, 0.1, log=True, nominal=0.02, unit="s"),
    Param("dampratio", 0.05, 3.0, log=True, nominal=1.0),
    Param("dmin", 0.0001, 0.9999, log=False, nominal=0.9),
    Param("dmax", 0.0001, 0.9999, log=False, nominal=0.95),
    Param("width", 1e-4, 0.05, log=True, nominal=0.001, unit="m"),
)
_STATE = mjtState.mjSTATE_FULLPHYSICS  # time, qpos (7), qvel (6): columns 1-3 centre, 4-7 quaternion


def _model(table_height: float, dt: float, params: dict[str, float]) -> MjModel:
    h, inertia = HALF_EXTENT, INERTIA
    cx, cy, cz = (float(c) for c in com_offset(params))  # (float: numpy's repr is not MJCF)
    xml = f"""<mujoco>
  <option timestep="{dt / SUBSTEPS!r}" gravity="0 0 {-GRAVITY!r}"/>
  <worldbody>
    <geom name="table" type="plane" size="0 0 1" pos="0 0 {table_height!r}"/>
    <body name="cube">
      <freejoint/>
      <inertial pos="{cx!r} {cy!r} {cz!r}" mass="{MASS!r}" diaginertia="{inertia!r} {inertia!r} {inertia!r}"/>
      <geom name="cube" type="box" size="{h!r} {h!r} {h!r}"/>
    </body>
  </worldbody>
</mujoco>"""
    model = MjModel.from_xml_string(xml)
    model.geom_friction[:, 0] = params["friction"]
    model.geom_solref[:] = (params["timeconst"], params["dampratio"])
    model.geom_solimp[:, :3] = (params["dmin"], params["dmax"], params["width"])
    return model


def simulate(tosses: Tosses, params: dict[str, float], table_height: float) -> tuple[np.ndarray, np.ndarray]:
    """Each toss rolled out from its first recorded frame for its length: position (F, 3) m, quaternion (F, 4)
    w, x, y, z, one row per recorded frame (frame 0 the recorded one). params: the names of ``PARAMETERS``, all
    given, and of ``cube.COM_PARAMETERS`` (m), each 0 when absent; table_height: the table plane's z in m. The frames
    from where MuJoCo reset an unstable rollout on are NaN (a reset leaves finite states that are not the toss's)."""
    check_params(params, PARAMETERS + COM_PARAMETERS, ENGINE, optional=COM_NAMES)
    model = _model(table_height, tosses.dt, params)
    data = MjData(model)
    size = mj_stateSize(model, _STATE)

    def run_group(index: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray]:
        start = np.zeros((len(index), size))
        for j, i in enumerate(index):
            f = int(tosses.offsets[i])
            mj_resetData(model, data)
            data.qpos[:] = np.concatenate([tosses.position[f], tosses.quaternion[f]])
            data.qvel[:] = np.concatenate([tosses.velocity[f], tosses.omega[f]])
            mj_getState(model, data, start[j], _STATE)
        states = start[:, None]
        if frames > 1:
            nstep = (frames - 1) * SUBSTEPS
            out, _ = rollout.rollout(model, data, start, nstep=nstep)
            out = cast(np.ndarray, out)  # (the states (B, nstep, size): mujoco types them as any array-like or None)
            # MuJoCo resets an unstable simulation (a non-finite or huge acceleration) to the model's reference pose
            # and goes on: finite states that are not the toss's. The reset sets the time back, so every step from
            # the first whose time is not its own is unstable, and its frames are returned as NaN, not as poses.
            h = model.opt.timestep
            lost = np.logical_or.accumulate(np.abs(out[..., 0] - h * np.arange(1, nstep + 1)) > 0.5 * h, axis=1)
            out = np.where(lost[..., None], np.nan, out)
            states = np.concatenate([states, out[:, SUBSTEPS - 1 :: SUBSTEPS]], axis=1)
        return states[..., 1:4], states[..., 4:8]

    return roll_out_groups(tosses, run_group)

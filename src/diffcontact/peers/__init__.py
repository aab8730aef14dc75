"""Peers of the real-data benchmark: the ContactNets cube on a table simulated in MuJoCo and in Bullet, their contact
parameters fitted to the training tosses by CMA-ES (as Acosta et al., RA-L 2022, fitted MuJoCo, Drake and Bullet).

Each engine module (``mujoco_cube``, ``bullet_cube``) has ``PARAMETERS`` (the fitted ones, with bounds and nominal
values) and ``simulate(tosses, params, table_height) -> (position (F, 3), quaternion (F, 4))``; ``fit.run_fit`` is
the command's library call. The engines and the optimiser are optional (``pip install -e '.[peers]'``): load an
engine module with ``load_engine``.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from diffcontact.errors import ConfigError, DiffContactError

ENGINES = {"mujoco": "mujoco", "bullet": "pybullet"}  # engine name -> the package it needs
INSTALL = "pip install -e '.[peers]'"


class MissingPeerPackageError(DiffContactError, ImportError):
    """A package of the optional ``peers`` group (mujoco, pybullet, cma) is not installed."""


def require(package: str) -> ModuleType:
    """Import ``package`` of the ``peers`` group, or raise MissingPeerPackageError saying how to install it."""
    try:
        return importlib.import_module(package)
    except ModuleNotFoundError as err:
        raise MissingPeerPackageError(f"the peers need the package {package!r}, not installed: {INSTALL}") from err


def load_engine(name: str) -> ModuleType:
    """The engine module of ``name`` (mujoco or bullet); ConfigError for another name, MissingPeerPackageError
    when its package is not installed."""
    if name not in ENGINES:
        raise ConfigError(f"engine {name!r} is not one of {', '.join(ENGINES)}")
    require(ENGINES[name])
    return importlib.import_module(f"diffcontact.peers.{name}_cube")

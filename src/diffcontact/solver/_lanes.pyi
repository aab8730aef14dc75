"""Type stub of the solver's compiled kernel (``csrc/lanes_module.cpp``, loaded and checked by ``lanes._load``).

Arrays are C-contiguous numpy buffers of the item sizes the kernel checks (float64, int64, bool); see the comments
of ``csrc/lanes_module.cpp`` for their shapes.
"""

import numpy as np

def solve(
    A: np.ndarray,
    T: np.ndarray,
    c: np.ndarray,
    lower: np.ndarray,
    on: np.ndarray,
    on_l: np.ndarray,
    idx: np.ndarray,
    trace: np.ndarray,
    out: np.ndarray,
    K: int,
    d: int,
    ipm_tol: float,
    final_tol: float,
    acceptable_tol: float,
    max_iter: int,
    start_margin: float,
    refine_tol: float,
    polish_steps: int,
    start: int,
    stop: int,
    /,
) -> None: ...
def adjoint(
    A: np.ndarray,
    T: np.ndarray,
    out: np.ndarray,
    on: np.ndarray,
    on_l: np.ndarray,
    g: np.ndarray,
    u: np.ndarray,
    v_l: np.ndarray,
    ok: np.ndarray,
    K: int,
    d: int,
    start: int,
    stop: int,
    /,
) -> None: ...
def flat(
    A: np.ndarray,
    mu: np.ndarray,
    active: np.ndarray,
    flags: np.ndarray,
    K: int,
    d: int,
    tol: float,
    start: int,
    stop: int,
    /,
) -> None: ...
def constants() -> dict[str, int | float]: ...
def supported() -> int: ...
def select(width: int, /) -> int: ...

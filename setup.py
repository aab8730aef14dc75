"""Build of the contact solver's compiled kernel (everything else is in pyproject.toml).

The kernel is the CPython extension module ``diffcontact.solver._lanes`` (``csrc/lanes_module.cpp``; called by
``solver/kernel.py``)."""

import glob

from setuptools import Extension, setup

CSRC = "src/diffcontact/solver/csrc/"

setup(
    ext_modules=[
        Extension(
            "diffcontact.solver._lanes",
            sources=[CSRC + f for f in ("lanes_module.cpp", "lanes_base.cpp", "lanes_avx2.cpp", "lanes_avx512.cpp")],
            depends=sorted(glob.glob(CSRC + "*.h*")),
            # IEEE arithmetic except errno, traps and fused multiply-adds: the kernel tests for NaN and inf itself
            extra_compile_args=["-O3", "-fno-math-errno", "-fno-trapping-math", "-ffp-contract=fast", "-fno-exceptions"]
            + ["-Wall"],
            language="c++",
        )
    ]
)

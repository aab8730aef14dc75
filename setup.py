"""Build of the contact solver's compiled kernel (everything else is in pyproject.toml).

The kernel is the CPython extension module ``diffcontact.solver._lanes`` (``csrc/lanes_module.cpp``; called by
``solver/kernel.py``). Its four sources compile at once, one per available CPU (the SIMD variants take 20-30 s
each at -O3), which halves an install on two cores."""

import glob
import os
from concurrent.futures import ThreadPoolExecutor

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

CSRC = "src/diffcontact/solver/csrc/"


class ParallelBuildExt(build_ext):
    """build_ext whose compiler compiles an extension's sources concurrently (setuptools' own ``-j`` runs whole
    extensions concurrently, and there is one)."""

    def build_extensions(self) -> None:
        compile_sources = self.compiler.compile
        jobs = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)

        def compile_each(sources, *args, **kwargs):
            with ThreadPoolExecutor(max(1, min(jobs, len(sources)))) as pool:
                done = pool.map(lambda source: compile_sources([source], *args, **kwargs), sources)
                return [obj for objects in done for obj in objects]

        self.compiler.compile = compile_each
        super().build_extensions()


setup(
    cmdclass={"build_ext": ParallelBuildExt},
    ext_modules=[
        Extension(
            "diffcontact.solver._lanes",
            sources=[CSRC + f for f in ("lanes_avx512.cpp", "lanes_avx2.cpp", "lanes_base.cpp", "lanes_module.cpp")],
            depends=sorted(glob.glob(CSRC + "*.h*")),
            # IEEE arithmetic except errno, traps and fused multiply-adds: the kernel tests for NaN and inf itself
            extra_compile_args=["-O3", "-fno-math-errno", "-fno-trapping-math", "-ffp-contract=fast", "-fno-exceptions"]
            + ["-Wall"],
            language="c++",
        )
    ],
)

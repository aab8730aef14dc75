"""The real package: ``python -m build`` makes an sdist holding the kernel's C++ sources and the task files, and a
wheel built from that sdist; the wheel, installed (not editable) into a fresh virtual environment, runs
``diffcontact simulate BP5-e`` from another directory with the task files and the kernel it ships.

Slow (about 1.5 to 2.5 minutes on 2 cores: compiling the kernel dominates).  The fresh environment reuses this
one's third-party packages (torch, lightning, ...) through a .pth line instead of downloading them, the way
``venv --system-site-packages`` would; with ``DIFFCONTACT_TEST_WHEEL_DEPS=1`` it installs them from the package
index instead (about 5 minutes more), so that the wheel's declared dependencies are checked too.
"""

from __future__ import annotations

import importlib.metadata
import os
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _run(cmd: list[str], cwd: Path, env: dict | None = None) -> str:
    done = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=1200)
    assert done.returncode == 0, f"{' '.join(map(str, cmd))} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done.stdout


@pytest.mark.slow
def test_the_wheel_installs_into_a_fresh_venv_and_simulates_from_another_directory(tmp_path):
    try:  # (the distribution, not ``import build``: the repository's build/ folder of build_ext imports as one)
        importlib.metadata.version("build")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("python -m build is in the dev extra: pip install -e '.[dev]'")
    source = tmp_path / "source"  # (a copy: no build/, egg-info or compiled kernel left in the work tree)
    source.mkdir()
    for name in ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md"):
        shutil.copy2(REPO / name, source / name)
    shutil.copytree(REPO / "src", source / "src", ignore=shutil.ignore_patterns("*.so", "__pycache__", "*.egg-info"))
    dist = tmp_path / "dist"
    _run([sys.executable, "-m", "build", "--outdir", str(dist), str(source)], cwd=tmp_path)  # sdist, then its wheel
    (sdist,), (wheel,) = dist.glob("*.tar.gz"), dist.glob("*.whl")
    with tarfile.open(sdist) as tar:
        in_sdist = {Path(n).relative_to(Path(n).parts[0]).as_posix() for n in tar.getnames() if "/" in n}
    csrc = {p.relative_to(REPO).as_posix() for p in (REPO / "src/diffcontact/solver/csrc").iterdir()}
    tasks = {p.relative_to(REPO).as_posix() for p in (REPO / "src/diffcontact/tasks").glob("*.toml")}
    assert csrc <= in_sdist and tasks <= in_sdist and "setup.py" in in_sdist
    with zipfile.ZipFile(wheel) as whl:
        in_wheel = set(whl.namelist())
    assert {t.removeprefix("src/") for t in tasks} <= in_wheel
    assert any(n.startswith("diffcontact/solver/_lanes") and n.endswith(".so") for n in in_wheel)
    assert not any("/csrc/" in n for n in in_wheel)  # (the sources stay in the sdist)

    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", str(venv)], cwd=tmp_path)
    python = venv / "bin" / "python"
    if os.environ.get("DIFFCONTACT_TEST_WHEEL_DEPS") == "1":
        _run([str(python), "-m", "pip", "install", "-q", str(wheel)], cwd=tmp_path)
    else:
        purelib = Path(_run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path))
        ours = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
        Path(purelib.as_posix().strip(), "_reuse_test_env.pth").write_text("\n".join(sorted(ours)) + "\n")
        _run(
            [str(python), "-m", "pip", "install", "-q", "--no-deps", "--no-index", "--ignore-installed", str(wheel)],
            tmp_path,
        )  # noqa: E501
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "DIFFCONTACT_TASKS", "VIRTUAL_ENV")}
    where = _run(
        [str(python), "-c", "import diffcontact as dc, diffcontact.solver.kernel as k; "
         "print(dc.__file__); print(dc.config.tasks_dir()); print(k._load().__file__)"],
        cwd=elsewhere, env=env,
    ).split()  # fmt: skip
    assert all(Path(p).is_relative_to(venv) for p in where), where  # (the installed copy, not the work tree)
    out = _run(
        [str(venv / "bin" / "diffcontact"), "simulate", "BP5-e", "--n", "4", "--out", "bp5e.npz"],
        cwd=elsewhere,
        env=env,
    )
    assert "wrote bp5e.npz: 4 trajectories x 100 frames of BP5-e" in out
    import numpy as np

    with np.load(elsewhere / "bp5e.npz") as data:
        assert data["x"].shape == (4, 100, 5, 2) and data["contact"].any()

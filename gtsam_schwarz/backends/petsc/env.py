"""Is PETSc over MPI usable here, and how to launch ``mpiexec`` (Open MPI's traps handled).

Nothing here imports petsc4py or mpi4py at module level: ``import gtsam_schwarz.backends.petsc``
works on a machine without them.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import shutil
import subprocess
import sys

PETSC_REQUIREMENT = "petsc4py==3.18.5 and mpi4py (pip install with PETSC_DIR set; see docs/distributed.md)"


def petsc_available(in_subprocess: bool = False) -> tuple[bool, str]:
    """(True, "") when petsc4py and mpi4py import; else (False, a one-line reason).

    ``in_subprocess``: try the import in a child Python, so that this process does not initialize
    PETSc and MPI (a test runner that only launches ``mpiexec`` children)."""
    for module in ("petsc4py", "mpi4py"):
        if importlib.util.find_spec(module) is None:
            return False, f"{module} is not installed (needs {PETSC_REQUIREMENT})"
    if in_subprocess:
        try:
            out = subprocess.run([sys.executable, "-c", "import petsc4py.PETSc, mpi4py.MPI"], capture_output=True,
                                 text=True, timeout=120, env=mpi_environment())
        except (OSError, subprocess.SubprocessError) as exc:
            return False, f"petsc4py/mpi4py import check failed: {exc}"
        if out.returncode != 0:
            last = (out.stderr.strip().splitlines() or [f"exit code {out.returncode}"])[-1]
            return False, f"petsc4py/mpi4py do not import: {last}"
        return True, ""
    try:
        import petsc4py  # noqa: F401
        from petsc4py import PETSc  # noqa: F401
        from mpi4py import MPI  # noqa: F401
    except Exception as exc:  # noqa: BLE001 — a broken build is "not available", with its reason
        return False, f"petsc4py/mpi4py do not import: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
    return True, ""


def mpiexec_path() -> str | None:
    """mpiexec (or mpirun) on PATH, or None."""
    return shutil.which("mpiexec") or shutil.which("mpirun")


@functools.lru_cache(maxsize=None)
def _is_open_mpi(exe: str) -> bool:
    try:
        out = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return False
    text = out.stdout + out.stderr
    return "Open MPI" in text or "OpenRTE" in text or "open-mpi" in text


def mpiexec_command(ranks: int, exe: str | None = None, oversubscribe: bool | None = None) -> list[str]:
    """``mpiexec -n K`` with the flags this machine needs: Open MPI refuses to run as root without
    ``--allow-run-as-root`` and refuses more ranks than cores without ``--oversubscribe``
    (added when ``ranks`` exceeds the cores, or when ``oversubscribe`` is True)."""
    exe = exe or mpiexec_path()
    if exe is None:
        raise FileNotFoundError("mpiexec/mpirun not found on PATH (Debian: apt-get install openmpi-bin)")
    cmd = [exe, "-n", str(int(ranks))]
    if _is_open_mpi(exe):
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            cmd.append("--allow-run-as-root")
        if oversubscribe or (oversubscribe is None and ranks > (os.cpu_count() or 1)):
            cmd.append("--oversubscribe")
    return cmd


def mpi_environment(env: dict | None = None) -> dict:
    """The environment for an mpiexec child: Open MPI's root permission, one BLAS/OpenMP thread per
    rank (the ranks are the parallelism), no shared-memory transport warnings in containers."""
    env = dict(os.environ if env is None else env)
    env.setdefault("OMPI_ALLOW_RUN_AS_ROOT", "1")
    env.setdefault("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
    env.setdefault("OMPI_MCA_rmaps_base_oversubscribe", "1")
    # containers often lack the ptrace permission for CMA single-copy; fall back quietly
    env.setdefault("OMPI_MCA_btl_vader_single_copy_mechanism", "none")
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(var, "1")
    return env


def launch_command(ranks: int, argv: list[str], oversubscribe: bool | None = None) -> list[str]:
    """``mpiexec -n K [flags] python -m gtsam_schwarz.backends.petsc.run ARGV``."""
    return mpiexec_command(ranks, oversubscribe=oversubscribe) + [
        sys.executable, "-m", "gtsam_schwarz.backends.petsc.run", *argv]


def mpi_ready(in_subprocess: bool = True) -> tuple[bool, str]:
    """(True, "") when petsc4py, mpi4py and mpiexec are all there, else the first missing one (the
    import is tried in a child Python unless ``in_subprocess`` is False)."""
    ok, why = petsc_available(in_subprocess)
    if not ok:
        return ok, why
    if mpiexec_path() is None:
        return False, "mpiexec/mpirun not found on PATH (Debian: apt-get install openmpi-bin)"
    return True, ""

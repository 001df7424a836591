import os
import pathlib

import gtsam
import numpy as np
import pytest

# GTSAM_SCHWARZ_DATASETS points elsewhere (e.g. at a missing folder, to check that the suite skips cleanly)
DATASETS = pathlib.Path(os.environ.get("GTSAM_SCHWARZ_DATASETS",
                                       pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "datasets"))
MISSING = f"needs the public datasets in {DATASETS} (absent here)"


def dataset(name: str) -> pathlib.Path:
    """Path of a public dataset in ../shared/datasets (CI has it beside the checkout); skips the
    calling test with a one-line reason when the folder is absent."""
    path = DATASETS / name
    if not DATASETS.is_dir():
        pytest.skip(MISSING)
    if not path.exists():
        pytest.fail(f"dataset {path} is missing from {DATASETS}")
    return path


def pytest_collection_modifyitems(config, items):
    """Tests marked ``datasets`` are skipped, with the reason, when ../shared/datasets is absent."""
    if DATASETS.is_dir():
        return
    skip = pytest.mark.skip(reason=MISSING)
    for item in items:
        if "datasets" in item.keywords:
            item.add_marker(skip)


def pose2_array(values: gtsam.Values) -> np.ndarray:
    return gtsam.utilities.extractPose2(values)


def pose2_difference(a: gtsam.Values, b: gtsam.Values) -> np.ndarray:
    """Per-pose (dx, dy, dθ) with the angle difference wrapped to (−π, π]."""
    d = pose2_array(a) - pose2_array(b)
    d[:, 2] = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return d


def gtsam_gauss_newton(graph, initial, iterations: int) -> gtsam.Values:
    """GTSAM's own Gauss–Newton for exactly ``iterations`` steps (error tolerances off)."""
    params = gtsam.GaussNewtonParams()
    params.setRelativeErrorTol(0.0)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(iterations)
    return gtsam.GaussNewtonOptimizer(graph, initial, params).optimize()


def run_cli(*args, cwd=None, timeout=600, env=None, **kw):
    """``python -m gtsam_schwarz.apps.cli ARGS`` in a child process, output captured as text."""
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "gtsam_schwarz.apps.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=timeout, env=env, **kw)


def one_line_error(proc, *words):
    """The command exited 2 with exactly one line on stderr (no traceback) containing ``words``."""
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for w in words:
        assert w in lines[0], lines[0]

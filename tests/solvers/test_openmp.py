"""CHOLMOD's OpenMP runtime is loaded with one thread, and the environment is left as it was."""

import json
import os
import subprocess
import sys

import pytest

PROBE = ("import json, os; from gtsam_schwarz.solvers import sparse; from gtsam_schwarz.solvers.openmp import limit_threads; "
         "print(json.dumps([limit_threads(), os.environ.get('OMP_THREAD_LIMIT')]))")


def _probe(env_extra: dict) -> list:
    env = {k: v for k, v in os.environ.items() if k != "OMP_THREAD_LIMIT"}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _have_gomp() -> bool:
    import ctypes
    try:
        ctypes.CDLL("libgomp.so.1")
        return True
    except OSError:
        return False


@pytest.mark.skipif(not _have_gomp(), reason="no libgomp on this machine: nothing to limit")
def test_one_thread_and_no_trace_in_the_environment():
    limit, left = _probe({})
    assert limit == 1
    assert left is None  # children (the bench's peers) do not inherit it


@pytest.mark.skipif(not _have_gomp(), reason="no libgomp on this machine: nothing to limit")
def test_a_limit_the_user_set_is_kept():
    assert _probe({"OMP_THREAD_LIMIT": "3"}) == [3, "3"]

"""The package's architecture, checked: layers import only downward, no cycles, and the Schwarz
core imports without gtsam (docs/architecture.md)."""

import ast
import pathlib
import subprocess
import sys

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "gtsam_schwarz"
CORE = ("dd", "coarse", "schwarz", "solvers", "krylov")
# what each layer may import from the package (besides itself); apps may import everything
ALLOWED = {
    "util": set(),  # array helpers: every layer may import them
    "io": set(), "problems": {"dd"}, "dd": set(), "solvers": set(), "krylov": set(),
    "coarse": {"dd", "solvers"}, "linearization": {"dd"}, "initialization": {"krylov", "solvers", "dd"},
    "schwarz": {"dd", "solvers", "coarse"},
    "nonlinear": {"dd", "solvers", "krylov", "coarse", "schwarz", "linearization", "initialization", "backends"},
    # a backend provides the nonlinear layer's LinearSolver interface on other machinery (PETSc over MPI)
    "backends": {"dd", "solvers", "krylov", "coarse", "schwarz", "linearization", "nonlinear", "io", "problems"},
}


def _module(path: pathlib.Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports() -> dict[str, set[str]]:
    """Module → package modules it imports (relative imports resolved)."""
    graph = {}
    for path in PACKAGE.rglob("*.py"):
        name = _module(path)
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")
                    base = base[:len(base) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target.startswith("gtsam_schwarz"):
                    found.add(target)
                    found.update(f"{target}.{a.name}" for a in node.names)
            elif isinstance(node, ast.Import):
                found.update(a.name for a in node.names if a.name.startswith("gtsam_schwarz"))
        graph[name] = found
    return graph


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def test_layers_import_only_downward():
    wrong = []
    for module, targets in _imports().items():
        layer = _layer(module)
        if layer in (None, "apps", "_compat"):
            continue
        for t in targets:
            other = _layer(t)
            if other is None or other == layer or other not in ALLOWED and other != "apps":
                continue
            if other == "apps" or other not in ALLOWED[layer] | {"util"}:
                wrong.append(f"{module} imports {t}")
    assert not wrong, "\n".join(sorted(wrong))


def test_no_module_outside_apps_imports_apps():
    users = [m for m, ts in _imports().items() if _layer(m) != "apps" and any(_layer(t) == "apps" for t in ts)
             and m != "gtsam_schwarz._compat"]
    assert not users


def test_no_import_cycles_between_modules():
    graph = _imports()
    modules = set(graph)
    edges = {m: {t for t in graph[m] if t in modules and t != m} for m in modules}
    # a package's __init__ importing its own modules is not a cycle of layers: drop parent → child
    edges = {m: {t for t in ts if not t.startswith(m + ".")} for m, ts in edges.items()}
    state, cycle = {}, []

    def visit(m, stack):
        state[m] = 1
        for t in sorted(edges[m]):
            if state.get(t) == 1:
                cycle.append(" → ".join(stack[stack.index(t):] + [t]) if t in stack else f"{m} → {t}")
            elif t not in state:
                visit(t, stack + [t])
        state[m] = 2

    for m in sorted(modules):
        if m not in state:
            visit(m, [m])
    assert not cycle, "\n".join(cycle)


@pytest.mark.parametrize("layer", CORE)
def test_core_imports_without_gtsam(layer):
    """With gtsam made unimportable, the Schwarz core still imports and solves a small system."""
    code = f"""
import sys
sys.modules["gtsam"] = None  # any `import gtsam` now raises ImportError
import gtsam_schwarz.{layer}
import numpy as np, scipy.sparse as sp
from gtsam_schwarz.dd import GraphStructure, decompose
from gtsam_schwarz.schwarz import make_preconditioner
from gtsam_schwarz.krylov import pcg
n = 60
A = sp.diags([-np.ones(n - 1), 2.01 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsr()
structure = GraphStructure.from_matrix(A, np.arange(n + 1))
M = make_preconditioner("gdsw", A, decompose(structure, 4, "segments"))
x, info = pcg(A, np.ones(n), M)
assert info.converged and info.iterations < 20, info
assert "gtsam" not in [m.split(".")[0] for m in sys.modules if sys.modules[m] is not None]
"""
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]


def test_old_module_paths_still_import_with_a_deprecation_warning():
    code = """
import warnings
warnings.simplefilter("error", DeprecationWarning)
try:
    from gtsam_schwarz.optimizer import SchwarzOptimizer
except DeprecationWarning as w:
    print("warned:", w)
warnings.simplefilter("ignore", DeprecationWarning)
from gtsam_schwarz.optimizer import SchwarzOptimizer, SchwarzParams
from gtsam_schwarz.preconditioners import make_preconditioner
from gtsam_schwarz.decomposition import decompose
import gtsam_schwarz as gs
assert SchwarzOptimizer is gs.SchwarzOptimizer
"""
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "warned: gtsam_schwarz.optimizer moved to gtsam_schwarz.nonlinear" in result.stdout

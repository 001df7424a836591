"""Old flat module paths (``gtsam_schwarz.optimizer``, …) as aliases of their new homes, with a
DeprecationWarning on import, so code written against the flat package keeps working."""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

MOVED = {
    "bars": "problems.bars", "problems": "problems", "io": "io",
    "files": "io.atomic", "linear_system": "linearization.gtsam_export",
    "decomposition": "dd", "interface": "dd.interface", "coarse": "coarse", "local_solvers": "solvers",
    "krylov": "krylov", "preconditioners": "schwarz", "optimizer": "nonlinear",
    "cli": "apps.cli", "commands": "apps.commands", "bench": "apps.bench", "paper": "apps.paper",
    "validation": "apps.validation", "compare": "apps.compare", "report": "apps.report",
    "plots": "apps.plots", "solve_plots": "apps.solve_plots", "runtime": "util.heap",
}
# names that are packages now but were modules with the same name: no alias needed
_SAME = {"problems", "io", "coarse", "krylov"}


class _AliasLoader(importlib.abc.Loader):
    def __init__(self, target: str):
        self.target = target

    def create_module(self, spec):
        return None  # a fresh module, filled with the new module's names below

    def exec_module(self, module):
        target = importlib.import_module(self.target)
        module.__dict__.update({k: v for k, v in vars(target).items() if not k.startswith("__")})


class _OldPaths(importlib.abc.MetaPathFinder):
    def __init__(self, package: str):
        self.package = package

    def find_spec(self, fullname, path=None, target=None):
        prefix = self.package + "."
        if not fullname.startswith(prefix):
            return None
        old = fullname[len(prefix):]
        if old not in MOVED or old in _SAME:
            return None
        new = f"{self.package}.{MOVED[old]}"
        warnings.warn(f"{fullname} moved to {new}; import it from there", DeprecationWarning, stacklevel=2)
        return importlib.util.spec_from_loader(fullname, _AliasLoader(new))


def install(package: str) -> None:
    if not any(isinstance(f, _OldPaths) for f in sys.meta_path):
        sys.meta_path.append(_OldPaths(package))

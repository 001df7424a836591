"""Linearization: the :class:`Linearizer` protocol (values + graph → H, g in a fixed block pattern,
retraction, error) and its implementations — GTSAM's (any factor) and the native vectorized one
(pose-graph factors). The GTSAM-dependent modules load on first use, so ``base`` and ``pattern``
import without gtsam.
"""

from importlib import import_module

from .base import Linearizer, LinearSystem
from .pattern import HessianPattern

_LAZY = {"GtsamLinearizer": "gtsam_export", "JacobianSystem": "gtsam_export", "KeyMap": "gtsam_export",
         "export_linear_system": "gtsam_export", "NativeLinearizer": "native"}

__all__ = ["HessianPattern", "LinearSystem", "Linearizer", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        return getattr(import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

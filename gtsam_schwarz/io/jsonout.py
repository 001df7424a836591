"""JSON output: NaN/inf become null (JSON has neither), records and numpy scalars plain Python."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np


def json_safe(obj):
    """``obj`` with non-finite floats → None, recursively through mappings (dicts, iteration records),
    lists, tuples and numpy arrays; numpy scalars become Python numbers."""
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, Mapping):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    return obj

"""JSON output: non-finite floats become null (JSON has no NaN), records become plain dicts."""

from __future__ import annotations

import math
from collections.abc import Mapping


def json_safe(obj):
    """``obj`` with NaN/inf → None, recursively through dicts, mappings (iteration records) and lists."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj

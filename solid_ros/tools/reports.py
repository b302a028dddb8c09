"""JSON reports of the offline tools: plain types, non-finite numbers as null."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ['jsonable', 'write_json']


def jsonable(obj: Any) -> Any:
    """``obj`` with numpy scalars as Python numbers and NaN / inf as None (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    return obj


def write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as indented strict JSON (OSError propagates)."""
    path.write_text(json.dumps(jsonable(obj), indent=2) + '\n', encoding='utf-8')

"""Tests of the JSON report helpers."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from solid_ros.tools.reports import jsonable, write_json


def test_numpy_and_non_finite_values_become_strict_json(tmp_path: Path) -> None:
    obj = {1: np.int64(3), 'f': np.float32(0.5),
           'bad': [math.nan, math.inf, (np.float64(-math.inf),)], 'ok': 'text'}
    assert jsonable(obj) == {'1': 3, 'f': 0.5, 'bad': [None, None, [None]], 'ok': 'text'}
    path = tmp_path / 'r.json'
    write_json(path, obj)
    text = path.read_text()
    assert 'NaN' not in text and 'Infinity' not in text
    assert json.loads(text)['bad'] == [None, None, [None]]

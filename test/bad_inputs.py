"""Malformed inputs shared by the tests of several modules: parameter files, unusable clouds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

BAD_FILES = {
    'missing': None,
    'directory': 'DIR',
    'unparsable': b'solid_node:\n  ros__parameters: [1, 2\n',
    'binary': bytes(range(256)) * 4,
    'latin1': 'solid_node:\n  ros__parameters:\n    session_id: 1 # \xe9t\xe9\n'.encode('latin-1'),
    'top-level list': b'- solid_node\n- ros__parameters\n',
    'empty': b'',
    'comments only': b'# nothing here\n',
    'no ros__parameters': b'solid_node:\n  fov_width_deg: 90.0\n',
    'other node only': b'other_node:\n  ros__parameters:\n    fov_width_deg: 90.0\n',
    'integer for float': b'solid_node:\n  ros__parameters:\n    fov_width_deg: 90\n',
    'float for integer': b'solid_node:\n  ros__parameters:\n    num_range: 40.0\n',
    'deep nesting': b'solid_node: ' + b'[' * 5000 + b']' * 5000 + b'\n',
    'bad date': b'solid_node:\n  ros__parameters:\n    session_id: 2001-13-45\n',
}


def write_bad_file(tmp_path: Path, name: str) -> Path:
    """The parameter file of ``BAD_FILES[name]`` (shared with the node's tests)."""
    path = tmp_path / (name.replace(' ', '_') + '.yaml')
    blob = BAD_FILES[name]
    if blob == 'DIR':
        path.mkdir()
    elif isinstance(blob, bytes):
        path.write_bytes(blob)
    return path


def unusable_clouds(n: int = 1200, max_range: float = 80.0,
                    ) -> dict[str, npt.NDArray[np.floating]]:
    """Clouds that decode but hold no point a detector with ``max_range`` can use."""
    rng = np.random.default_rng(5)
    mixed = rng.choice(np.array([np.nan, np.inf, -np.inf], dtype=np.float32), size=(n, 3))
    far = rng.normal(size=(n, 3))
    far *= 2.0 * max_range / np.linalg.norm(far, axis=1, keepdims=True)
    return {
        'empty': np.zeros((0, 3), dtype=np.float32),
        'all NaN': np.full((n, 3), np.nan, dtype=np.float32),
        'all inf': np.full((n, 3), np.inf, dtype=np.float32),
        'all -inf': np.full((n, 3), -np.inf),
        'all 1e38': np.full((n, 3), 1e38, dtype=np.float32),
        'all zeros': np.zeros((n, 3), dtype=np.float32),
        'NaN, inf and -inf': mixed,
        'beyond max_range': far,
        'one NaN coordinate each': np.where(np.eye(3, dtype=bool)[np.arange(n) % 3], np.nan,
                                            rng.normal(scale=10.0, size=(n, 3))),
    }

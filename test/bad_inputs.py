"""Malformed inputs shared by the tests of several modules (parameter files for now)."""

from __future__ import annotations

from pathlib import Path

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

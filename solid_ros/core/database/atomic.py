"""Writing a file so that a crash leaves the old one or the new one, never a torn one.

Writing goes to a temporary file in the target directory, which is flushed, fsynced and then
renamed over the target. The temporary file is locked while it is written; one left by a killed
save is removed by the next save of the same target (:func:`remove_stale_temporaries`).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO

from solid_ros.core.errors import SolidError

__all__ = ['fsync_dir', 'remove_stale_temporaries', 'write_atomic']


def write_atomic(target: str | Path, write: Callable[[IO[bytes]], object], *,
                 check: Callable[[Path], None] | None = None, what: str = 'file',
                 error: type[SolidError] = SolidError) -> Path:
    """Write through ``write(file)`` to a locked temporary file beside ``target``, then rename
    it over ``target``: a crash leaves the old file or the new one, never a torn one.

    The lock tells :func:`remove_stale_temporaries` that the file is in use; it is held until
    the rename is done.

    Args:
        target: the file to write.
        write: writes the content into the open temporary file.
        check: called with ``target`` just before the rename (may raise to keep the old file).
        what: the kind of file, for the error message.
        error: the error class raised.

    Raises:
        SolidError: (``error``) the file cannot be written.
    """
    path = Path(target)
    tmp_name = ''
    try:
        directory = path.parent.resolve()  # not path.resolve(): never follow a link
        fd, tmp_name = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp',
                                        dir=directory)
        with os.fdopen(fd, 'wb') as f:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX)
            write(f)
            f.flush()
            os.fsync(f.fileno())
            if check is not None:
                check(path)  # again, just before replacing it
            os.replace(tmp_name, path)
            tmp_name = ''
        fsync_dir(directory)
    except OSError as err:
        raise error(f'cannot write {what} {path}: {err.strerror or err}') from err
    finally:
        if tmp_name:
            with contextlib.suppress(OSError):
                os.unlink(tmp_name)
    return path


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Remove temporary files that killed saves of ``path`` left behind.

    Only files named like this module's temporaries of ``path`` are considered, and only
    those no live save holds locked.

    Returns:
        The files removed.
    """
    target = Path(path)
    pattern = re.compile(re.escape(f'.{target.name}.') + r'[a-z0-9_]{8}\.tmp')
    removed: list[Path] = []
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return removed
    for entry in entries:
        if not pattern.fullmatch(entry.name) or not entry.is_file(follow_symlinks=False):
            continue
        try:
            fd = os.open(entry.path, os.O_RDWR | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            os.unlink(entry.path)
            removed.append(Path(entry.path))
        except OSError:
            continue  # a save in progress holds the lock
        finally:
            os.close(fd)
    return removed


def fsync_dir(directory: Path) -> None:
    """Make the rename durable (POSIX); not possible everywhere, so best effort."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)

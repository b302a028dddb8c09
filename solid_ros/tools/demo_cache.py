"""The demo's cache of simulated drives: one directory per drive under ``~/.cache``.

``solid_demo`` simulates a drive once and replays the cached bag afterwards. An entry is named
by the drive's :meth:`~solid_ros.sim.DriveConfig.fingerprint` and the package version and
holds what :func:`solid_ros.sim.write_drive` writes (bag, reference poses, times, labels,
drive.json).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from solid_ros.core.errors import BagError
from solid_ros.sim import DEMO_DEFAULTS, Drive, DriveConfig, write_drive

__all__ = ['cache_root', 'demo_dir', 'ensure_demo_bag']


def cache_root() -> Path:
    """``$XDG_CACHE_HOME/solid_ros/demo`` (``~/.cache/solid_ros/demo`` by default)."""
    base = os.environ.get('XDG_CACHE_HOME') or str(Path.home() / '.cache')
    return Path(base) / 'solid_ros' / 'demo'


def demo_dir(config: DriveConfig, cache_dir: str | Path | None = None) -> Path:
    """Directory a drive is cached in: ``<root>/<sensor>-<hash of config and version>``."""
    from solid_ros import __version__

    root = Path(cache_dir) if cache_dir is not None else cache_root()
    tag = f'{config.fingerprint()}-{__version__}'
    return root / f'{config.model.name}-{tag}'


def ensure_demo_bag(cache_dir: str | Path | None = None, **options: Any) -> Path:
    """Return the demo bag, simulating and writing it first if it is not cached yet.

    The drive is written into a temporary directory beside the cache entry and renamed into
    place, so an interrupted run never leaves a half-written entry behind.

    Args:
        cache_dir: cache root; :func:`cache_root` when omitted.
        **options: :class:`DriveConfig` fields overriding :data:`DEMO_DEFAULTS`.

    Returns:
        Path of the bag directory; ``poses.txt``, ``times.txt``, ``labels.txt`` and
        ``drive.json`` sit in its parent.

    Raises:
        BagError: the cache directory cannot be written.
    """
    config = DriveConfig(**{**DEMO_DEFAULTS, **options})
    target = demo_dir(config, cache_dir)
    bag = target / 'bag'
    if (bag / 'metadata.yaml').is_file():
        return bag
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f'.{target.name}.', dir=target.parent))
    except OSError as err:
        raise BagError(f'cannot create cache directory {target.parent}: {err}') from err
    try:
        write_drive(tmp, Drive(config))
        try:
            os.rename(tmp, target)
        except OSError:
            # Another run finished first: keep its entry.
            if not (bag / 'metadata.yaml').is_file():
                raise
    except OSError as err:
        raise BagError(f'cannot write demo bag into {target}: {err}') from err
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return bag

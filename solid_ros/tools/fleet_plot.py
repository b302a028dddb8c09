"""The fleet map's plot: every placed robot's path in robot 0's map frame and the inter-robot
loops between them (matplotlib, Agg backend; imported only when plotting)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt

from solid_ros.core.results import LoopCandidate
from solid_ros.tools.fleet_map import FleetTrajectory
from solid_ros.tools.plots import pyplot

__all__ = ['FLEET_PLOT', 'write_fleet_plot']

FLEET_PLOT = 'fleet_map.png'
_COLOURS = ('#2c7fb8', '#d95f0e', '#7570b3', '#1b9e77', '#e7298a', '#66a61e', '#a6761d')
_TRUE, _FALSE = '#1b9e4b', '#d7301f'


def _positions(trajs: Sequence[FleetTrajectory]) -> dict[tuple[int, int], npt.NDArray[np.float64]]:
    """Fleet-frame position of each placed keyframe by ``(robot, stamp_ns)``."""
    return {(t.robot, int(s)): p[:3, 3] for t in trajs if t.placed
            for s, p in zip(t.stamps_ns, t.poses)}


def write_fleet_plot(path: str | Path, trajs: Sequence[FleetTrajectory],
                     published: Sequence[Sequence[LoopCandidate]],
                     errors: Sequence[Sequence[tuple[float, float]]],
                     max_error: tuple[float, float]) -> Path:
    """Draw the placed robots' paths and their inter-robot loops (green: correct against the
    reference within ``max_error`` metres and degrees, red: not) and save to ``path``."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 6.5), dpi=110)
    where = _positions(trajs)
    for t in trajs:
        if not t.placed or not len(t.poses):
            continue
        colour = _COLOURS[t.robot % len(_COLOURS)]
        xy = t.poses[:, :3, 3]
        ax.plot(xy[:, 0], xy[:, 1], '-', color=colour, lw=1.4, label=f'robot {t.robot}')
        ax.plot(xy[0, 0], xy[0, 1], '^', color=colour, ms=7)
    counts = {True: 0, False: 0}
    for robot, loops in enumerate(published):
        for c, (te, re_) in zip(loops, errors[robot]):
            a = where.get((robot, c.query_stamp_ns))
            b = where.get((c.match_session, c.match_stamp_ns))
            if c.match_session == robot or a is None or b is None:
                continue
            ok = bool(te < max_error[0] and re_ < max_error[1])
            counts[ok] += 1
            ax.plot([a[0], b[0]], [a[1], b[1]], '-', color=_TRUE if ok else _FALSE,
                    lw=0.9, alpha=0.7, zorder=5)
    ax.plot([], [], '-', color=_TRUE, label=f'inter-robot loop, correct ({counts[True]})')
    ax.plot([], [], '-', color=_FALSE, label=f'inter-robot loop, false ({counts[False]})')
    out = [t.robot for t in trajs if not t.placed]
    ax.set(xlabel='x (m)', ylabel='y (m)', title="Fleet map: robot 0's map frame"
           + (f' (not placed: robot {", ".join(map(str, out))})' if out else ''))
    ax.set_aspect('equal', adjustable='datalim')
    ax.grid(alpha=0.3)
    ax.legend(loc='best', fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)

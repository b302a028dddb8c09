"""PNG plots of a replay evaluation (matplotlib, Agg backend; imported only when plotting)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.tools.evaluation import Evaluation
from solid_ros.tools.loops import LoopRecord

__all__ = ['PLOT_FILES', 'pyplot', 'write_plots']

PLOT_FILES = ('pr_curve.png', 'trajectory.png', 'distance_hist.png', 'yaw_error_hist.png',
              'verification.png', 'pose_error_hist.png')
_TRUE, _FALSE, _GREY = '#1b9e4b', '#d7301f', '#9a9a9a'


def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (imported on first use)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    return plt


def _pr(plt: Any, ev: Evaluation, threshold: float, path: Path) -> None:
    c = ev.curve
    m = ev.metrics()
    fig, ax = plt.subplots(figsize=(6, 5), dpi=110)
    if c.thresholds.size:
        ax.plot(np.concatenate(([0.0], c.recall)), np.concatenate(([1.0], c.precision)),
                color='#2c7fb8', lw=2, drawstyle='steps-post', label='best match per query')
        f1, tau, k = ev.f1_max()
        if k >= 0:
            ax.plot(c.recall[k], c.precision[k], 'o', color=_TRUE, ms=9,
                    label=f'F1max {f1:.3f} at distance {tau:.4f}')
        _, zr, kz = ev.zero_fp()
        if kz >= 0:
            ax.plot(c.recall[kz], c.precision[kz], 's', color='#fd8d3c', ms=8,
                    label=f'zero-FP: recall {zr:.3f}')
        op = np.searchsorted(c.thresholds, threshold, side='left') - 1
        if op >= 0:
            ax.plot(c.recall[op], c.precision[op], 'x', color='black', ms=10, mew=2,
                    label=f'configured threshold {threshold:g}')
    auc = m['roc_auc']
    ax.set(xlim=(-0.02, 1.02), ylim=(-0.02, 1.05), xlabel='recall', ylabel='precision',
           title=f'Precision-recall ({m["queries_with_true_loop"]} true-loop queries, '
                 f'ROC AUC {auc:.3f})' if auc is not None else 'Precision-recall')
    ax.grid(alpha=0.3)
    ax.legend(loc='lower left', fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


_ESTIMATES = {'odometry': ('#fd8d3c', '--'), 'corrected': ('#2c7fb8', '-')}


def _segments(ax: Any, pos: npt.NDArray[np.float64], pairs: Sequence[tuple[int, int]],
              **style: Any) -> None:
    """Draw the edges ``pairs`` (rows of ``pos``) as one line broken by NaN: one artist, where
    a line per edge (hku1: hundreds) made the legend's placement and the layout cost seconds."""
    if not pairs:
        return
    ends = np.asarray(pairs, dtype=np.intp)
    xy = np.full((len(ends), 3, 2), np.nan)
    xy[:, 0], xy[:, 1] = pos[ends[:, 0], :2], pos[ends[:, 1], :2]
    ax.plot(xy[:, :, 0].ravel(), xy[:, :, 1].ravel(), '-', **style)


def _trajectory(plt: Any, ev: Evaluation, pos: npt.NDArray[np.float64],
                match: npt.NDArray[np.intp], records: Sequence[LoopRecord] | None,
                max_error: tuple[float, float], path: Path,
                estimates: Mapping[str, npt.NDArray[np.float64]] | None = None) -> None:
    fig, ax = plt.subplots(figsize=(6.5, 6), dpi=110)
    ax.plot(pos[:, 0], pos[:, 1], '-', color=_GREY, lw=1,
            label='reference' if estimates else 'trajectory')
    for name, est in (estimates or {}).items():
        colour, style = _ESTIMATES.get(name, ('black', ':'))
        ax.plot(est[:, 0], est[:, 1], style, color=colour, lw=1.4, alpha=0.95, zorder=4,
                label=f'{name} (aligned to the reference)')
    pos_q = np.flatnonzero(ev.truth.has_loop)
    ax.plot(pos[pos_q, 0], pos[pos_q, 1], '.', color='#74a9cf', ms=4,
            label=f'queries with a true loop ({len(pos_q)})')
    if records is None:  # edges of the accepted best matches
        edges = [(int(q), int(match[q]), bool(ev.correct[q]))
                 for q in np.flatnonzero(ev.accepted & (match >= 0))]
        rejected: list[tuple[int, int]] = []
    else:
        inside = [r for r in records if r.session >= 0 and 0 <= r.match < len(pos)
                  and np.isfinite(r.trans_err_m)]
        edges = [(r.query, r.match, r.correct(*max_error)) for r in inside if r.published]
        rejected = [(r.query, r.match) for r in inside if not r.published]
    faint = 0.1 if estimates else 0.25  # the trajectories must stay visible beneath them
    _segments(ax, pos, rejected, color=_GREY, lw=0.5, alpha=faint)
    counts = {True: 0, False: 0}
    for ok in (True, False):
        pairs = [(q, m) for q, m, good in edges if good == ok]
        counts[ok] = len(pairs)
        _segments(ax, pos, pairs, color=_TRUE if ok else _FALSE, lw=1.6 if ok else 1.2,
                  alpha=0.85)
    what = 'published loop' if records is not None else 'accepted loop'
    if rejected:
        ax.plot([], [], '-', color=_GREY, alpha=0.5, label=f'rejected candidate ({len(rejected)})')
    ax.plot([], [], '-', color=_TRUE, label=f'{what}, correct ({counts[True]})')
    ax.plot([], [], '-', color=_FALSE, label=f'{what}, false ({counts[False]})')
    if len(pos):
        ax.plot(pos[0, 0], pos[0, 1], 'k^', ms=7, label='start')
    ax.set(xlabel='x (m)', ylabel='y (m)', title='Trajectory and loop edges'
           + (' (edges on the reference)' if estimates else ''))
    ax.set_aspect('equal', adjustable='datalim')
    ax.grid(alpha=0.3)
    ax.legend(loc='best', fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _verification(plt: Any, records: Sequence[LoopRecord] | None, min_overlap: float | None,
                  path: Path) -> None:
    """Structure overlap of the candidates that reached fine registration."""
    fig, ax = plt.subplots(figsize=(6.5, 4.5), dpi=110)
    recs = list(records or [])
    ov_v = np.array([r.overlap for r in recs if r.verified and np.isfinite(r.overlap)])
    ov_r = np.array([r.overlap for r in recs if not r.verified and np.isfinite(r.overlap)])
    early = sum(1 for r in recs if not r.verified and not np.isfinite(r.overlap))
    bins = np.linspace(0.0, 1.0, 41)
    ax.hist(ov_v, bins=bins, color=_TRUE, alpha=0.7, label=f'verified ({ov_v.size})')
    ax.hist(ov_r, bins=bins, color=_FALSE, alpha=0.5,
            label=f'rejected after fine registration ({ov_r.size})')
    if min_overlap is not None:
        ax.axvline(min_overlap, color='black', ls='--', lw=1.2,
                   label=f'verify_min_overlap {min_overlap:g}')
    ax.plot([], [], ' ', label=f'rejected before it, not shown ({early})')
    ax.set(xlabel='structure overlap', ylabel='candidates',
           title='Verified vs rejected candidates')
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _pose_errors(plt: Any, records: Sequence[LoopRecord] | None,
                 max_error: tuple[float, float], path: Path) -> None:
    """Translation and rotation error of the published loops against the reference pose."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), dpi=110)
    pub = [r for r in records or [] if r.published and np.isfinite(r.trans_err_m)]
    ok = np.array([r.correct(*max_error) for r in pub], dtype=bool)
    errors = (np.array([r.trans_err_m for r in pub]), np.array([r.rot_err_deg for r in pub]))
    for ax, err, limit, unit in zip(axes, errors, max_error, ('m', 'deg')):
        if err.size:
            # False loops can be off by tens of metres: larger errors go into the last bin.
            top = max(2.0 * limit, min(float(err.max()), 10.0 * limit))
            bins = np.linspace(0.0, top * 1.0001, 41)
            clipped = np.minimum(err, top)
            ax.hist([clipped[ok], clipped[~ok]], bins=bins, stacked=True,
                    color=[_TRUE, _FALSE], alpha=0.8,
                    label=[f'correct ({int(ok.sum())})', f'false ({int((~ok).sum())})'])
            ax.axvline(limit, color='black', ls='--', lw=1.2, label=f'limit {limit:g} {unit}')
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, 'no published loop with a reference', ha='center',
                    va='center', transform=ax.transAxes)
        what = 'translation' if unit == 'm' else 'rotation'
        ax.set(xlabel=f'{what} error ({unit}; the last bin holds larger ones)',
               ylabel='published loops', title=f'Published loops: {what} error')
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _distances(plt: Any, ev: Evaluation, threshold: float, path: Path) -> None:
    sel = ev.has_best & ev.truth.valid
    d = ev.distance[sel]
    ok = ev.correct[sel]
    fig, ax = plt.subplots(figsize=(6.5, 4.5), dpi=110)
    hi = float(np.nanmax(d)) if d.size else 1.0
    bins = np.linspace(0.0, max(hi, threshold) * 1.02 + 1e-9, 40)
    ax.hist(d[ok], bins=bins, color=_TRUE, alpha=0.7, label=f'true match ({int(ok.sum())})')
    ax.hist(d[~ok], bins=bins, color=_FALSE, alpha=0.6,
            label=f'false match ({int((~ok).sum())})')
    ax.axvline(threshold, color='black', ls='--', lw=1.2, label=f'configured {threshold:g}')
    _, tau, _ = ev.f1_max()
    if tau is not None:
        ax.axvline(tau, color='#2c7fb8', ls=':', lw=1.6, label=f'F1max at {tau:.4f}')
    ax.set(xlabel='cosine distance of the best match', ylabel='queries',
           title='Best-match distance: true vs false matches')
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _yaw(plt: Any, ev: Evaluation, path: Path) -> None:
    e = ev.yaw_error_deg[np.isfinite(ev.yaw_error_deg)]
    fig, ax = plt.subplots(figsize=(6.5, 4.5), dpi=110)
    if e.size:
        ax.hist(e, bins=np.linspace(0.0, max(float(e.max()), 1.0) * 1.02, 30), color='#756bb1')
        ax.axvline(float(np.median(e)), color='black', ls='--',
                   label=f'median {np.median(e):.2f} deg')
        ax.axvline(float(np.percentile(e, 95)), color='#d95f0e', ls=':',
                   label=f'95th percentile {np.percentile(e, 95):.2f} deg')
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, 'no true matches', ha='center', va='center', transform=ax.transAxes)
    ax.set(xlabel='|yaw error| (deg)', ylabel='true matches',
           title=f'Yaw error over true best matches (n={e.size})')
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_plots(out_dir: str | Path, ev: Evaluation, positions: npt.ArrayLike,
                match: npt.ArrayLike, threshold: float,
                records: Sequence[LoopRecord] | None = None,
                max_error: tuple[float, float] = (1.0, 3.0),
                min_overlap: float | None = None,
                estimates: Mapping[str, npt.ArrayLike] | None = None) -> list[Path]:
    """Write the evaluation plots and return their paths.

    Args:
        out_dir: existing directory.
        ev: evaluation of the replay.
        positions: (K, 3) reference positions per keyframe.
        match: (K,) best match per keyframe (this session), -1 when none.
        threshold: the configured distance_threshold (marked on the plots).
        records: scored candidates (published loops, rejected ones); None draws the
            accepted best matches instead.
        max_error: translation (m) and rotation (deg) limits of a correct loop.
        min_overlap: the configured ``verify_min_overlap`` (marked; None without
            verification).
        estimates: (K, 3) positions per keyframe drawn beside the reference on the
            trajectory plot, by name (``'odometry'``, ``'corrected'``), already aligned.
    """
    plt = pyplot()
    out = Path(out_dir)
    pos = np.asarray(positions, dtype=np.float64)
    m = np.asarray(match, dtype=np.intp)
    paths = [out / name for name in PLOT_FILES]
    _pr(plt, ev, threshold, paths[0])
    est = {k: np.asarray(v, dtype=np.float64) for k, v in (estimates or {}).items()}
    _trajectory(plt, ev, pos, m, records, max_error, paths[1], est)
    _distances(plt, ev, threshold, paths[2])
    _yaw(plt, ev, paths[3])
    _verification(plt, records, min_overlap, paths[4])
    _pose_errors(plt, records, max_error, paths[5])
    return paths

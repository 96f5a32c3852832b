"""The multilevel fit: level 0 maps the feature points with a global RBF, then each level
adds an offset with half the previous support (f_k = f_{k-1} + o_k), scored by
E = alpha Ed + beta Em; the level where E is smallest is kept.

How a level finds its offset is the refinement scheme's business
(:class:`~tpscore.adaptation.surface.SurfaceLevels` by default,
:class:`~tpscore.adaptation.interpolate.InterpolatedLevels` for the published method): a
scheme has ``finished(support)`` and ``fit(level, support, fields, deformed, normals)``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..csrbf import ConvergenceError
from ..rbf import RBF
from .fit_error import LevelScore, LevelScorer
from .options import AdaptOptions
from .result import AdaptLevel, Correspondences
from .setup import AdaptSetup

__all__ = ["LevelFit", "Levels", "fit_levels"]


@dataclass(frozen=True)
class LevelFit:
    """What one level found: its field and the fit it gives."""

    method: str
    """"rbf", "csrbf" or "surface"."""
    support: float
    """sigma_k (mm); NaN for a global RBF."""
    field: Callable
    """Level 0's map, or the level's offset (template-frame points -> mm)."""
    deformed: np.ndarray
    """(n, 3) the template's vertices under the levels so far, template frame."""
    pairs: tuple
    """(template points, scan points, source names) the level was fitted to."""
    new_pairs: int
    anchors: np.ndarray | None = None
    """The vertices paired with the scan (``"surface"`` levels only): the fill's anchors."""


@dataclass(frozen=True)
class Levels:
    """The levels computed and the one kept."""

    reports: list
    """An :class:`AdaptLevel` per level computed."""
    fields: tuple
    """The field of each level computed."""
    best_level: int
    best: LevelFit

    @property
    def anchors(self) -> np.ndarray:
        return self.best.anchors if self.best.anchors is not None else np.zeros(0, dtype=np.int64)

    @property
    def correspondences(self) -> Correspondences:
        template_points, scan_points, source = self.best.pairs
        return Correspondences(template_points.copy(), scan_points.copy(), np.asarray(source, dtype=str))


def fit_levels(setup: AdaptSetup, options: AdaptOptions, scheme, progress, log) -> Levels:
    """Level 0, then the scheme's levels while the supports allow and E keeps falling
    (every level with ``stop_at_minimum=False``)."""
    width = setup.width
    threshold = options.distance_threshold if options.distance_threshold is not None else width / 10.0
    scorer = LevelScorer(setup.template_faces, setup.scan_tree, setup.target.vertex_normals,
                         setup.target.rim_vertices, threshold=threshold, vertex_weights=options.vertex_weights,
                         markers=setup.markers, covered=setup.covered, scale=setup.transform.scale,
                         alpha=options.alpha, beta=options.beta)

    start = time.perf_counter()
    first = RBF(setup.landmark_sources, setup.landmark_targets, "biharmonic", smoothing=options.rho)
    count = len(setup.landmark_sources)
    pairs = (setup.landmark_sources.copy(), setup.landmark_targets.copy(),
             np.array(["landmark"] * count, dtype=object))
    best = current = LevelFit("rbf", float("nan"), first, first(setup.template_vertices), pairs, count)
    fields = [first]
    score = scorer(fields, current.deformed)
    reports = [_report(0, current, score, start, progress)]
    best_level, best_error = 0, score.error

    support = float(options.initial_support) if options.initial_support is not None else width / 5.0
    for level in range(1, options.levels):
        start = time.perf_counter()
        if scheme.finished(support):
            break
        try:
            fit = scheme.fit(level, support, tuple(fields), current.deformed, score.normals)
        except ConvergenceError:
            log(f"level {level}: the CSRBF solve did not converge; the fit stops at level {level - 1}")
            break
        fields.append(fit.field)
        score = scorer(fields, fit.deformed)
        reports.append(_report(level, fit, score, start, progress))
        support /= 2.0
        if np.isfinite(score.error) and score.error < best_error or not np.isfinite(best_error):
            best_level, best_error, best = level, score.error, fit
        elif options.stop_at_minimum:
            break
        current = fit
    return Levels(reports, tuple(fields), best_level, best)


def _report(level: int, fit: LevelFit, score: LevelScore, start: float, progress) -> AdaptLevel:
    report = AdaptLevel(level, fit.method, fit.support, len(fit.pairs[0]), fit.new_pairs, score.distance_error,
                        score.marker_error, score.error, score.coverage, time.perf_counter() - start)
    if progress:
        progress(report)
    return report

"""What a template adaptation returns: the fitted template, the figures of each level,
the pairs it used and the warnings it gave."""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from .._validation import as_points
from ..face.normalise import FrameTransform

__all__ = ["AdaptationWarning", "AdaptLevel", "AdaptResult", "Correspondences", "WarningLog",
           "evaluate_fields"]


class AdaptationWarning(UserWarning):
    """Part of an adaptation cannot be trusted (holes, wrong or missing feature points, noise)."""


class WarningLog:
    """The warnings of one adaptation, given together when it ends so that each points at
    the caller's line, and kept in :attr:`AdaptResult.warnings`."""

    def __init__(self):
        self.messages: list[str] = []

    def __call__(self, message: str) -> None:
        self.messages.append(message)

    def emit(self, stacklevel: int) -> None:
        for message in self.messages:
            warnings.warn(message, AdaptationWarning, stacklevel=stacklevel + 1)


@dataclass(frozen=True)
class AdaptLevel:
    """The figures of one level of the multilevel fit (a row of the method's Tables 1-2)."""

    level: int
    method: str
    """"rbf" (global biharmonic), "csrbf" or "surface"."""
    support: float
    """Support sigma_k (mm, template frame); NaN for a global level."""
    pairs: int
    """Correspondences the level's offset was fitted to."""
    new_pairs: int
    """Of those, the pairs found at this level."""
    distance_error: float
    """Ed, mm^2 (scan frame)."""
    marker_error: float
    """Em, mm^2 (scan frame); NaN without held-out markers."""
    error: float
    """E = alpha Ed + beta Em."""
    coverage: float
    """Fraction of the template vertices in the feature points' bounding box that have a
    compatible scan vertex."""
    seconds: float
    """Time spent on the level (pairing, fit, evaluation and error)."""


@dataclass(frozen=True)
class Correspondences:
    """The template -> scan pairs the fit used, in the template frame."""

    template_points: np.ndarray
    """(n, 3) points on the undeformed template, mm."""
    scan_points: np.ndarray
    """(n, 3) the scan points they were paired with (calibrated frame), mm."""
    source: np.ndarray
    """(n,) str: "landmark", "feature-mesh", "curvature" or "surface"."""


def evaluate_fields(fields, points: np.ndarray) -> np.ndarray:
    """f(points) = f_0(points) + the sum of the offsets: the map of a multilevel fit."""
    result = fields[0](points)
    for offset in fields[1:]:
        result = result + offset(points)
    return result


@dataclass(frozen=True)
class AdaptResult:
    """The template fitted to a scan.

    Attributes
    ----------
    vertices : (n, 3) ndarray
        The deformed template, vertex for vertex, in the SCAN's frame (mm).
    template_frame_vertices : (n, 3) ndarray
        The same, in the template's frame (before undoing the calibration).
    transform : FrameTransform
        The calibration: scan frame -> template frame.
    levels : list of AdaptLevel
        Every level computed, including the one that made E rise (if any).
    best_level : int
        The level whose fit is returned (E at its minimum).
    correspondences : Correspondences
        The pairs of the returned level.
    outlier_landmarks : tuple of int
        Feature points left out of the fit as wrong.
    warnings : tuple of str
        The :class:`AdaptationWarning` messages given.
    fields : tuple of callables
        The map of each level in :attr:`levels`: level 0's RBF (template-frame
        points to their place on the scan), then each level's offset.
    """

    vertices: np.ndarray
    template_frame_vertices: np.ndarray
    transform: FrameTransform
    levels: list
    best_level: int
    correspondences: Correspondences
    outlier_landmarks: tuple = ()
    warnings: tuple = ()
    fields: tuple = field(default=(), repr=False)

    def deform(self, points, level: int | None = None) -> np.ndarray:
        """Apply the fitted map to template-frame points.

        The map is defined in space, so it does not include the snap and the fill of
        the ``"surface"`` refinement, which act on the template's vertices.

        Parameters
        ----------
        points : (m, 3) array_like
            Points in the template's frame (mm).
        level : int, optional
            Apply the levels up to this one; default :attr:`best_level`.

        Returns
        -------
        (m, 3) ndarray in the scan's frame (mm).
        """
        points = as_points(points, "points")
        level = self.best_level if level is None else level
        if isinstance(level, bool) or int(level) != level or not 0 <= level < len(self.fields):
            raise ValueError(f"level must be one of the computed levels 0..{len(self.fields) - 1}, got {level!r}")
        return self.transform.apply_inverse(evaluate_fields(self.fields[: int(level) + 1], points))

    def __repr__(self) -> str:
        best = next((lv for lv in self.levels if lv.level == self.best_level), None)
        error = f", E {best.error:.3g}" if best is not None else ""
        return (f"AdaptResult({len(self.vertices)} vertices, best level {self.best_level} of "
                f"{len(self.levels)}{error}, {len(self.correspondences.template_points)} pairs, "
                f"{len(self.outlier_landmarks)} outlier landmarks, {len(self.warnings)} warnings)")

    def table(self) -> str:
        """The per-level figures as a Markdown table."""
        rows = ["| level | method | sigma (mm) | pairs | Ed (mm^2) | Em (mm^2) | E | coverage | time (s) |",
                "|---|---|---|---|---|---|---|---|---|"]
        for lv in self.levels:
            mark = " *" if lv.level == self.best_level else ""
            rows.append(f"| {lv.level}{mark} | {lv.method} | {lv.support:.1f} | {lv.pairs} | "
                        f"{lv.distance_error:.3f} | {lv.marker_error:.3f} | {lv.error:.3f} | "
                        f"{lv.coverage:.2f} | {lv.seconds:.3f} |")
        return "\n".join(rows)

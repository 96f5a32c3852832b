"""The correspondence between the target and the source: which point of the source's
neutral face each target point reads its motion at (``TransferOptions.correspondence``).

``"landmarks"`` (the default) is a TPS through the 22 landmark pairs (and, where the
motion is cut at openings, the openings' edges). ``"adapted"`` fits the target's
neutral grid onto the source's neutral scan with the template adaptation
(:func:`tpscore.adapt`: a global RBF through the landmark pairs, then compactly
supported offsets that pull every visible vertex onto the other surface), so that
between the landmarks the map follows the two faces' shapes rather than a smooth
guess; it meets the lips and lids without the edge pairs (they measured no better
with them, benchmarks/FIDELITY.md). It costs about a second per pair of faces, once:
it is kept with the target face for the source face it was fitted to.
"""
from __future__ import annotations

import warnings
import weakref

import numpy as np

from ..adaptation import AdaptOptions, AdaptationWarning, adapt
from ..face.grid import FaceGrid
from ..face.landmarks import landmark_map
from ..face.normalise import NormalisedFace

__all__ = ["CORRESPONDENCES", "ADAPT_SPACING_MM", "landmark_correspondence", "adapted_correspondence"]

#: ``"landmarks"``: the landmark TPS; ``"adapted"``: the target's neutral grid adapted
#: onto the source's neutral scan (see the module's text).
CORRESPONDENCES = ("landmarks", "adapted")

#: The adaptation fits the target's grid thinned to about this spacing (mm): the map is
#: defined in space and its finest offsets span several millimetres, so the thinned
#: grid gives the same map (development subjects, AU12 and happiness: 0.132 and 0.179
#: from every third row and column of a 1.2 mm grid, 0.133 and 0.177 from all of them)
#: in a fifth of the time.
ADAPT_SPACING_MM = 3.5


def landmark_correspondence(target: NormalisedFace, source: NormalisedFace, extra, merge_mm: float,
                            smoothing: float):
    """The landmark TPS target -> source, through ``extra`` (target points, source
    points; None: no more pairs) too."""
    return landmark_map(target.landmarks, source.landmarks, merge_mm=merge_mm, what="target -> source",
                        extra=extra, smoothing=smoothing)


def adapted_correspondence(target: NormalisedFace, source: NormalisedFace):
    """The map target -> source of the target's grid adapted onto the source's surface
    through their landmarks; kept with the target for this source face, so that the
    next transfer between the same two faces (a rig's other expressions, a batch's
    other codes) reuses it."""
    key = ("adapted correspondence", id(source))
    owner, deform = target.derived(key, lambda face: (weakref.ref(source), _fit_adapted(face, source)))
    if owner() is not source:   # another face now has the id of the one it was fitted to
        deform = _fit_adapted(target, source)
    return deform


def _fit_adapted(target: NormalisedFace, source: NormalisedFace):
    grid = target.grid
    step = max(1, int(round(ADAPT_SPACING_MM / _spacing(grid))))
    template = FaceGrid.from_points(grid.points[::step, ::step], grid.mask[::step, ::step]).mesh()
    # both faces are in the reference frame already; a poor fit shows in the transfer's
    # scores, not as the adaptation's warnings about a template and a scan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AdaptationWarning)
        fitted = adapt((template.vertices, template.faces), source.grid.mesh(), target.landmarks,
                       source.landmarks, options=AdaptOptions(calibration="none"))
    return _finite_rows(fitted.deform)


def _finite_rows(deform):
    """``deform`` on (m, 3) points, NaN rows (a mirror image off the grid) left NaN."""
    def apply(points):
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.full(points.shape, np.nan)
        finite = np.isfinite(points).all(axis=1)
        if finite.any():
            out[finite] = deform(points[finite])
        return out
    return apply


def _spacing(grid: FaceGrid) -> float:
    """The median distance (mm) between neighbouring valid vertices along a row."""
    steps = np.linalg.norm(np.diff(grid.points, axis=1), axis=2)
    steps = steps[np.isfinite(steps)]
    return float(np.median(steps)) if len(steps) else ADAPT_SPACING_MM

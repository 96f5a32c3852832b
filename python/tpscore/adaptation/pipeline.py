"""The template adaptation from end to end: :func:`adapt` runs the stages in order."""
from __future__ import annotations

from typing import Callable

import numpy as np

from .fill import fill_unseen
from .interpolate import InterpolatedLevels
from .levels import Levels, fit_levels
from .options import AdaptOptions
from .result import AdaptLevel, AdaptResult, WarningLog, evaluate_fields
from .rigid import move_rigid_parts
from .setup import AdaptSetup, prepare
from .snap import snap_onto_scan
from .surface import SurfaceLevels

__all__ = ["adapt"]

# Below this fraction of the template's feature region near scan data, the rest of the
# fit is interpolation over holes or beyond the scan's edge.
_LOW_COVERAGE = 0.75


def adapt(template, scan, template_landmarks, scan_landmarks=None, *, options: AdaptOptions = AdaptOptions(),
          progress: Callable[[AdaptLevel], None] | None = None) -> AdaptResult:
    """Fit a template mesh to a scan: the template's topology, the scan's shape.

    Stages: calibrate the scan into the template's frame; fit level 0, a global
    biharmonic RBF through the feature points; add refinement levels with halving
    supports while the error E = alpha Ed + beta Em falls; then, with the default
    ``"surface"`` refinement, snap the visible vertices onto the scan and fill the
    unseen ones along the mesh; last, move the rigid parts. docs/adaptation.md
    describes each stage and its measurements.

    Parameters
    ----------
    template : (vertices, faces), FaceGrid or GridMesh
        The template mesh (mm), any topology; faces consistently oriented with
        normals facing out of the face (toward +z in the template frame).
    scan : (vertices, faces), FaceGrid, GridMesh or BntScan
        The scan surface (mm), in its own frame; noise and holes allowed.
    template_landmarks : (k, 3) array_like, or (k,) int vertex indices
        Feature points on the template (NaN rows or -1 missing). With k = 22 they are
        the Bosphorus landmarks, which the axes calibration and the named feature box
        need.
    scan_landmarks : (k, 3) array_like, optional
        The corresponding scan points (NaN rows missing); defaults to the FaceGrid's
        landmarks when `scan` is a FaceGrid.
    options : AdaptOptions
        How to fit; :meth:`AdaptOptions.published` is the method as published.
    progress : callable, optional
        Called with each finished :class:`AdaptLevel`.

    Returns
    -------
    AdaptResult

    Raises
    ------
    ValueError
        Bad arguments, or fewer than 5 usable feature pairs.

    Warns
    -----
    AdaptationWarning
        Where the result cannot be trusted: missing or wrong feature points, little
        scan data near the template, a noisy scan, or no level better than level 0.
    """
    if not isinstance(options, AdaptOptions):
        raise ValueError(f"options must be an AdaptOptions, got {type(options).__name__}")
    log = WarningLog()
    setup = prepare(template, scan, template_landmarks, scan_landmarks, options, log)
    scheme = (SurfaceLevels if options.refinement == "surface" else InterpolatedLevels)(setup, options)
    levels = fit_levels(setup, options, scheme, progress, log)

    deformed = levels.best.deformed.copy()
    anchors = levels.anchors
    refined_on_surface = options.refinement == "surface" and levels.best_level > 0
    if refined_on_surface and options.snap:
        deformed, anchors = snap_onto_scan(setup, deformed, options.snap_rings)
    if refined_on_surface and options.fill_unseen:
        deformed = fill_unseen(setup.template_vertices, setup.template_faces, deformed, anchors)
    best_fields = levels.fields[: levels.best_level + 1]
    if options.rigid_parts:
        move_rigid_parts(deformed, setup.template_vertices, options.rigid_parts, setup.landmark_sources,
                         evaluate_fields(best_fields, setup.landmark_sources))

    _warn_about_the_result(setup, options, levels, log)
    log.emit(stacklevel=2)
    return AdaptResult(setup.transform.apply_inverse(deformed), deformed, setup.transform, levels.reports,
                       levels.best_level, levels.correspondences, setup.outliers, tuple(log.messages),
                       levels.fields)


def _warn_about_the_result(setup: AdaptSetup, options: AdaptOptions, levels: Levels, log) -> None:
    final = levels.reports[levels.best_level]
    if final.coverage < _LOW_COVERAGE:
        log(f"only {100 * final.coverage:.0f}% of the template has scan data near it (holes or a "
            "partial scan); the rest is interpolated and cannot be trusted")
    if np.isfinite(setup.scan_noise) and setup.scan_noise > options.noise_warning_mm:
        log(f"the scan is noisy (about {setup.scan_noise:.2f} mm along its normals); the fit follows it only "
            "as far as rho and csrbf_smoothing allow; raise them if the result is rough")
    if levels.best_level == 0 and options.levels > 1:
        log("no refinement level lowered the error; the result is the feature-point RBF alone")

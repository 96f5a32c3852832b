"""The options of a template adaptation: one frozen dataclass, validated when it is made.

The defaults are the settings that measured best on the adaptation benchmark
(docs/adaptation.md); :meth:`AdaptOptions.published` is the method as published.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._validation import as_points, check_options
from ..face.landmarks import landmark_index
from ..face.normalise import FrameTransform
from .calibration import CALIBRATION_METHODS

__all__ = ["AdaptOptions", "DEFAULT_FEATURE_BOX", "REFINEMENTS"]

#: Landmarks whose bounding box (plus a margin) limits the curvature search: eyes to mouth.
DEFAULT_FEATURE_BOX = (
    "Outer left eye corner", "Outer right eye corner", "Inner left eye corner", "Inner right eye corner",
    "Nose tip", "Left mouth corner", "Right mouth corner", "Lower lip outer middle",
)

#: How the levels after level 0 use the scan: point to plane onto the closest scan points
#: (the default), or the published interpolation of ray-paired correspondences.
REFINEMENTS = ("surface", "interpolate")


@dataclass(frozen=True)
class AdaptOptions:
    """How :func:`tpscore.adapt` fits a template to a scan.

    Every field is checked when the options are made (``dataclasses.replace`` checks
    again), so a bad value fails before any work is done. The measurements behind the
    defaults are in docs/adaptation.md.

    Attributes
    ----------
    levels : int
        Largest number of levels, >= 1 (level 0 is the feature points' RBF).
    refinement : {"surface", "interpolate"}
        The levels after level 0. ``"surface"``: each level is a Wendland offset
        fitted point to plane to the closest scan points of every visible template
        vertex (a regularised non-rigid ICP step), then the snap and the fill.
        ``"interpolate"``: the published scheme, which interpolates the residuals at
        feature-mesh and curvature correspondences paired by rays (see
        :meth:`published`); it ties every pair's sliding to the feature points and
        measured worse.
    calibration : {"similarity", "axes", "none"} or FrameTransform
        How the scan is brought into the template's frame: a least-squares
        similarity over the feature pairs, the method's axes calibration, nothing
        (both already share a frame), or a given transform (scan -> template).
    rho : float
        Error coefficient of the global RBF levels (K - rho I), mm, >= 0; it smooths
        the feature points' annotation noise.
    initial_support : float, optional
        sigma_1 (mm, template frame), halved at every level; default a fifth of the
        template's width.
    min_support : float, optional
        The ``"surface"`` levels stop once sigma_k falls below this (mm, template
        frame); default a tenth of the template's width (finer levels cost seconds
        and gain little).
    surface_iterations : int
        Closest-point / solve rounds per ``"surface"`` level.
    regularisation : float
        lambda, > 0: weight of the offset's native norm relative to one surface pair.
    landmark_weight : float
        Weight of each feature point in the ``"surface"`` levels, in surface pairs;
        small, so that the surface overrides the feature points' annotation error.
    centre_spacing : float
        Spacing of the ``"surface"`` offset's centres, as a fraction of sigma_k.
    snap : bool
        After a ``"surface"`` fit, move every visible paired vertex along its normal
        onto the scan's tangent plane at its closest point: the finest level leaves
        fine relief (lip and alar creases, eyelids) a few tenths of a millimetre short.
    snap_rings : int
        One-ring averages of the snap distances over the paired neighbours, >= 0,
        against scan noise.
    fill_unseen : bool
        After a ``"surface"`` fit, give the template vertices that were never paired
        (inside the nostrils, between the lips, over holes) the harmonic fill, along
        the template mesh, of the paired vertices' displacements, instead of what
        the field carries over from other parts of the face nearby in space.
    csrbf_smoothing : float
        Diagonal term of the ``"interpolate"`` CSRBF levels, >= 0, against scan noise.
    curvature_count : int
        Curvature vertices paired at each ``"interpolate"`` level (0: none).
    feature_box : sequence of landmark names, or ((3,), (3,)) corners, or None
        Limits the ``"interpolate"`` curvature search (template frame): the bounding
        box of the named landmarks plus a margin, or two corners; None: the whole
        template. Names need the 22 Bosphorus landmarks.
    scan_view : (3,) array_like or None
        Direction from the scan toward its scanner, in the scan's frame (+z for
        Bosphorus); template points facing away from it cannot have been scanned and
        are not paired. None disables the test.
    outlier_threshold : float
        Leave-one-out miss (mm), > 0, above which a feature point is judged wrong and
        left out. Correct landmarks miss by up to about 13 mm on the development
        subjects (identity differences the others do not predict).
    held_out_landmarks : sequence of landmark names or row indices
        Feature points kept out of the fit and used as markers for Em.
    markers : (template_points (m, 3), scan_points (m, 3)), optional
        More marker pairs for Em (template frame, scan frame), never fitted.
    alpha, beta : float
        Weights of Ed and Em in E = alpha Ed + beta Em, >= 0.
    distance_threshold : float, optional
        Ed's compatibility distance (mm); default a tenth of the template's width.
    vertex_weights : (n,) array_like, optional
        Per-vertex (region) weights of Ed, >= 0.
    stop_at_minimum : bool
        Stop at the first level where E rises; False runs every level. Either way
        the level with the smallest E is returned.
    noise_warning_mm : float
        Warn when the estimated scan noise exceeds this (mm), > 0.
    rigid_parts : sequence of vertex index arrays, optional
        Groups of template vertices (eyes, teeth) that move rigidly: each follows the
        similarity fitted to the six feature points nearest to it.
    """

    levels: int = 6
    refinement: str = "surface"
    calibration: str | FrameTransform = "similarity"
    rho: float = 30.0
    initial_support: float | None = None
    min_support: float | None = None
    surface_iterations: int = 2
    regularisation: float = 5.0
    landmark_weight: float = 0.3
    centre_spacing: float = 1.0 / 3.0
    snap: bool = True
    snap_rings: int = 1
    fill_unseen: bool = True
    csrbf_smoothing: float = 2.0
    curvature_count: int = 300
    feature_box: tuple | None = DEFAULT_FEATURE_BOX
    scan_view: tuple | None = (0.0, 0.0, 1.0)
    outlier_threshold: float = 15.0
    held_out_landmarks: tuple = ()
    markers: tuple | None = field(default=None, compare=False, repr=False)
    alpha: float = 1.0
    beta: float = 1.0
    distance_threshold: float | None = None
    vertex_weights: np.ndarray | None = field(default=None, compare=False, repr=False)
    stop_at_minimum: bool = True
    noise_warning_mm: float = 0.6
    rigid_parts: tuple | None = field(default=None, compare=False, repr=False)
    # markers, vertex_weights and rigid_parts hold per-point or per-vertex arrays: they are
    # left out of comparisons (arrays have no single truth value) and of the one-line repr.

    def __post_init__(self):
        optional = [name for name in ("initial_support", "min_support", "distance_threshold")
                    if getattr(self, name) is not None]
        choices = {"refinement": REFINEMENTS}
        if not isinstance(self.calibration, FrameTransform):
            choices["calibration"] = CALIBRATION_METHODS
        check_options(self, positive=("regularisation", "centre_spacing", "outlier_threshold",
                                      "noise_warning_mm", *optional),
                      non_negative=("rho", "landmark_weight", "csrbf_smoothing", "alpha", "beta"),
                      counts=("levels", "surface_iterations", ("snap_rings", 0), ("curvature_count", 0)),
                      flags=("snap", "fill_unseen", "stop_at_minimum"), choices=choices)
        # The fields below hold data rather than numbers; each is converted once, here.
        convert = {"feature_box": _feature_box, "scan_view": _scan_view,
                   "held_out_landmarks": _held_out, "markers": _markers,
                   "vertex_weights": _vertex_weights, "rigid_parts": _rigid_parts}
        for name, converter in convert.items():
            value = getattr(self, name)
            if value is None:
                continue
            try:
                converted = converter(value)
            except (TypeError, ValueError) as error:
                if str(error).startswith("AdaptOptions."):
                    raise
                # NumPy's and Python's own conversion errors do not say which field failed.
                raise ValueError(f"AdaptOptions.{name}: {error}") from None
            object.__setattr__(self, name, converted)

    @classmethod
    def published(cls, **changes) -> "AdaptOptions":
        """The template adaptation as published (docs/design.md, method 2): the scan calibrated
        by the feature points' axes (R = Rz Ry Rx, the scale from a reference axis); a
        global biharmonic RBF with an affine part (K - rho I) through the feature points;
        then levels f_k = f_{k-1} + o_k with halving supports, each o_k interpolating the
        residuals at the level's correspondences -- a global RBF while they are fewer
        than 500, after that a compactly supported Wendland RBF with a local quadric in
        each centre's tangent frame (Ohtake, Belyaev and Seidel 2004). Each level adds
        the feature mesh's new points (every triangle split at its barycentre, rays
        along its normal onto both surfaces; Kaehler et al. 2002) and the template
        vertices of largest mean curvature (Meyer et al. 2003) inside the feature box,
        paired by rays along their normals; the levels stop when E = alpha Ed + beta Em
        stops falling. What the method leaves open (rho, the supports, the CSRBF
        smoothing, the curvature count) keeps the defaults.

        Kept as the reference the default is measured against: on the adaptation
        benchmark it is less accurate (docs/adaptation.md). The axes calibration and
        the feature box need the 22 Bosphorus landmarks, the calibration at least the
        chin, an eye corner and a left/right pair; ``published(calibration="similarity")``
        does without.

        Parameters
        ----------
        **changes
            Fields to set differently (e.g. ``calibration="none"`` for a scan already
            in the template's frame).
        """
        return cls(**{"refinement": "interpolate", "calibration": "axes", **changes})


def _feature_box(box) -> tuple:
    items = tuple(box)
    if items and all(isinstance(item, str) for item in items):
        for name in items:
            _check_landmark_name(name, "feature_box")
        return items
    corners = np.asarray(items, dtype=np.float64) if len(items) == 2 else None
    if corners is None or corners.shape != (2, 3) or not np.isfinite(corners).all():
        raise ValueError("AdaptOptions.feature_box must be landmark names, two (3,) corners or None, "
                         f"got {box!r}")
    return tuple(float(v) for v in corners[0]), tuple(float(v) for v in corners[1])


def _check_landmark_name(name: str, field_name: str) -> None:
    try:
        landmark_index(name)
    except ValueError as error:
        raise ValueError(f"AdaptOptions.{field_name}: {error}") from None


def _scan_view(view) -> tuple:
    array = np.asarray(view, dtype=np.float64)
    if array.shape != (3,) or not np.isfinite(array).all() or not np.linalg.norm(array) > 0:
        raise ValueError(f"AdaptOptions.scan_view must be a non-zero (3,) direction or None, got {view!r}")
    return tuple(float(v) for v in array)


def _held_out(items) -> tuple:
    rows = []
    for item in items:
        if isinstance(item, str):
            _check_landmark_name(item, "held_out_landmarks")
        elif isinstance(item, (bool, np.bool_)) or not isinstance(item, (int, np.integer)) or item < 0:
            raise ValueError(f"AdaptOptions.held_out_landmarks: {item!r} is neither a landmark name nor a row")
        rows.append(item if isinstance(item, str) else int(item))
    return tuple(rows)


def _markers(markers) -> tuple:
    try:
        template_points, scan_points = markers
    except (TypeError, ValueError):
        raise ValueError("AdaptOptions.markers must be a (template_points, scan_points) pair") from None
    template_points = as_points(template_points, "AdaptOptions.markers template points", finite=False)
    scan_points = as_points(scan_points, "AdaptOptions.markers scan points", finite=False)
    if template_points.shape != scan_points.shape:
        raise ValueError("AdaptOptions.markers: template and scan points must have the same shape")
    return template_points, scan_points


def _vertex_weights(weights) -> np.ndarray:
    array = np.array(weights, dtype=np.float64).reshape(-1)
    if not np.isfinite(array).all() or (array < 0).any():
        raise ValueError("AdaptOptions.vertex_weights must be finite non-negative numbers")
    array.setflags(write=False)
    return array


def _rigid_parts(parts) -> tuple:
    converted = []
    for k, part in enumerate(parts):
        indices = np.array(part).reshape(-1)
        if indices.size and not np.issubdtype(indices.dtype, np.integer):
            raise ValueError(f"AdaptOptions.rigid_parts[{k}] must hold vertex indices")
        indices = indices.astype(np.int64)
        if indices.size and indices.min() < 0:
            raise ValueError(f"AdaptOptions.rigid_parts[{k}] has a negative vertex index")
        indices.setflags(write=False)
        converted.append(indices)
    return tuple(converted)

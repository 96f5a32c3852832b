"""The first stage of an adaptation: read the inputs once, choose the feature points that
take part, calibrate the scan into the template's frame, and fix the scales every later
stage works with."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validation import as_faces, as_points
from ..face.grid import FaceGrid, GridMesh
from ..face.io import BntScan
from ..face.landmarks import LANDMARK_NAMES, N_LANDMARKS, landmark_index
from ..face.normalise import FrameTransform
from ..rbf import RBF
from ..spatial import KDTree, MeshSurface
from .calibration import calibrate
from .correspondence import ScanTarget
from .fit_error import surface_noise
from .options import AdaptOptions

__all__ = ["AdaptSetup", "find_outlier_landmarks", "prepare"]

# Fewer feature pairs than this cannot fix the global RBF's affine part robustly.
_MIN_FEATURE_PAIRS = 5


@dataclass(frozen=True)
class AdaptSetup:
    """Everything the levels, the snap and the fill share, in the template's frame (mm)."""

    template_vertices: np.ndarray
    template_faces: np.ndarray
    template_surface: MeshSurface
    target: ScanTarget
    """The scan, calibrated into the template's frame."""
    scan_tree: KDTree
    transform: FrameTransform
    """The calibration: scan frame -> template frame."""
    view: np.ndarray | None
    """Unit direction toward the scanner, template frame; None: no visibility test."""
    width: float
    """The template's extent along x: the unit of the default supports and distances."""
    max_ray: float
    """Longest pairing distance: farther, a ray finds another part of the face."""
    feature_points: np.ndarray
    """(k, 3) all template feature points (NaN rows missing)."""
    names: tuple | None
    """The Bosphorus landmark names when the feature points are the 22 landmarks."""
    landmark_sources: np.ndarray
    """(f, 3) the template feature points that take part in the fit."""
    landmark_targets: np.ndarray
    """(f, 3) their scan partners (calibrated, moved onto the scan's surface)."""
    markers: tuple
    """(template points (m, 3), calibrated scan points (m, 3)) for Em."""
    covered: np.ndarray
    """(n,) bool: the vertices inside the fitted feature points' bounding box."""
    outliers: tuple
    """Feature point rows left out as wrong."""
    scan_noise: float
    """Estimated noise of the scan along its normals (mm), NaN if unknown."""


def prepare(template, scan, template_landmarks, scan_landmarks, options: AdaptOptions, log) -> AdaptSetup:
    """Check and convert the inputs, calibrate the scan and pair the feature points.

    Raises ValueError naming the argument for bad input, and when fewer than 5 feature
    pairs are usable.
    """
    template_vertices, template_faces = as_mesh(template, "template")
    scan_vertices, scan_faces = as_mesh(scan, "scan")
    template_lm, scan_lm = _feature_point_arrays(template_landmarks, scan_landmarks, scan, template_vertices)
    _check_vertex_data(options, len(template_vertices))
    names = LANDMARK_NAMES if len(template_lm) == N_LANDMARKS else None
    label = (lambda i: names[i]) if names else (lambda i: f"feature point {i}")

    held = _held_out_rows(options.held_out_landmarks, len(template_lm))
    present = np.isfinite(template_lm).all(axis=1) & np.isfinite(scan_lm).all(axis=1)
    missing = np.flatnonzero(~present)
    if len(missing):
        log(f"{len(missing)} feature point(s) missing ({', '.join(label(i) for i in missing)}); "
            "the feature mesh and the curvature search fill in around them")
    fit_mask = present.copy()
    fit_mask[list(held)] = False
    transform, outliers = _calibrate(scan_lm, template_lm, fit_mask, options, names, label, log)
    if fit_mask.sum() < _MIN_FEATURE_PAIRS:
        raise ValueError(f"adaptation needs at least {_MIN_FEATURE_PAIRS} feature pairs present on both faces, "
                         f"got {int(fit_mask.sum())}")

    target = ScanTarget(transform.apply(scan_vertices), scan_faces)
    view = None
    if options.scan_view is not None:
        view = transform.apply_vectors(np.asarray(options.scan_view, dtype=np.float64))
        view = view / np.linalg.norm(view)
    width = float(np.ptp(template_vertices[:, 0]))
    max_ray = max(0.05 * width, 4.0)

    # Landmarks lie on the scan only to within their annotation error: move each onto the
    # surface (its normal error is pure noise) when the surface is close.
    scan_lm_calibrated = transform.apply(scan_lm)
    landmark_targets = scan_lm_calibrated[fit_mask].copy()
    closest = target.surface.closest_point(landmark_targets)
    near = closest.distances < 2.0 * max_ray
    landmark_targets[near] = closest.points[near]

    marker_rows = [i for i in sorted(held) if present[i]]
    marker_template, marker_scan = template_lm[marker_rows], scan_lm_calibrated[marker_rows]
    if options.markers is not None:
        marker_template = np.vstack([marker_template, options.markers[0]])
        marker_scan = np.vstack([marker_scan, transform.apply(options.markers[1])])

    # Coverage is judged over the part of the template the feature points span: a
    # template may reach well beyond what any scan of the face shows (ears, neck).
    fitted = template_lm[fit_mask]
    margin = 0.05 * width
    covered = np.all((template_vertices >= fitted.min(axis=0) - margin)
                     & (template_vertices <= fitted.max(axis=0) + margin), axis=1)
    noise = surface_noise(scan_vertices, scan_faces, target.vertex_normals)
    return AdaptSetup(template_vertices, template_faces, MeshSurface(template_vertices, template_faces), target,
                      KDTree(target.vertices), transform, view, width, max_ray, template_lm, names,
                      template_lm[fit_mask], landmark_targets, (marker_template, marker_scan), covered,
                      tuple(outliers), noise)


def as_mesh(obj, name: str):
    """(vertices, faces) from a FaceGrid, GridMesh, BntScan, MeshSurface or (vertices, faces)."""
    if isinstance(obj, FaceGrid):
        mesh = obj.mesh()
        return mesh.vertices, mesh.faces
    if isinstance(obj, GridMesh):
        return obj.vertices, obj.faces
    if isinstance(obj, BntScan):
        mesh = FaceGrid.from_points(obj.points).mesh()
        return mesh.vertices, mesh.faces
    if isinstance(obj, MeshSurface):
        return obj.vertices, obj.faces
    try:
        vertices, faces = obj
    except (TypeError, ValueError):
        raise ValueError(
            f"{name} must be a (vertices, faces) pair, a FaceGrid, a GridMesh or a BntScan, "
            f"got {type(obj).__name__}") from None
    vertices = as_points(vertices, f"{name} vertices", allow_empty=False)
    return vertices, as_faces(faces, len(vertices), f"{name} faces")


def as_feature_points(landmarks, vertices: np.ndarray, name: str) -> np.ndarray:
    """(k, 3) points with NaN rows; integer input (k,) are vertex indices (-1 missing)."""
    array = np.asarray(landmarks)
    if array.ndim == 1 and np.issubdtype(array.dtype, np.integer):
        index = array.astype(np.int64)
        if index.size and index.max() >= len(vertices):
            raise ValueError(f"{name}: vertex index {index.max()} is out of range ({len(vertices)} vertices)")
        points = np.full((len(index), 3), np.nan)
        points[index >= 0] = vertices[index[index >= 0]]
        return points
    return as_points(landmarks, name, finite=False)


def _feature_point_arrays(template_landmarks, scan_landmarks, scan, template_vertices):
    if scan_landmarks is None:
        if not isinstance(scan, FaceGrid):
            raise ValueError("scan_landmarks is required unless scan is a FaceGrid with landmarks")
        scan_landmarks = scan.landmarks
    template_lm = as_feature_points(template_landmarks, template_vertices, "template_landmarks")
    scan_lm = as_points(scan_landmarks, "scan_landmarks", finite=False)
    if scan_lm.shape != template_lm.shape:
        raise ValueError(f"scan_landmarks must have shape {template_lm.shape} like template_landmarks, "
                         f"got {scan_lm.shape}")
    return template_lm, scan_lm


def _check_vertex_data(options: AdaptOptions, n_vertices: int) -> None:
    """The options that hold per-vertex data must fit the template."""
    if options.vertex_weights is not None and len(options.vertex_weights) != n_vertices:
        raise ValueError(f"AdaptOptions.vertex_weights must hold {n_vertices} weights (one per template vertex), "
                         f"got {len(options.vertex_weights)}")
    for k, part in enumerate(options.rigid_parts or ()):
        if part.size and part.max() >= n_vertices:
            raise ValueError(f"AdaptOptions.rigid_parts[{k}] has vertex indices outside [0, {n_vertices})")


def _held_out_rows(items, k: int) -> set:
    rows = {landmark_index(item) if isinstance(item, str) else item for item in items}
    if rows and max(rows) >= k:
        raise ValueError(f"AdaptOptions.held_out_landmarks: row {max(rows)} is beyond the {k} feature points")
    return rows


def _calibrate(scan_lm, template_lm, fit_mask, options: AdaptOptions, names, label, log):
    """The calibration over the fitted feature pairs, and the wrong pairs it left out.

    A pair whose leave-one-out miss is too large is dropped from `fit_mask` (in place),
    and a method that fits the pairs calibrates again without it.
    """
    method = options.calibration
    if isinstance(method, str) and method == "axes" and names is None:
        raise ValueError("calibration='axes' needs the 22 Bosphorus landmarks")
    transform = calibrate(np.where(fit_mask[:, None], scan_lm, np.nan), template_lm, method)
    outliers = find_outlier_landmarks(np.where(fit_mask[:, None], template_lm, np.nan), transform.apply(scan_lm),
                                      threshold=options.outlier_threshold * transform.scale)
    if outliers:
        log(f"feature point(s) {', '.join(label(i) for i in outliers)} disagree with the others by more "
            f"than {options.outlier_threshold:g} mm and were left out of the fit; check them")
        fit_mask[outliers] = False
        if isinstance(method, str) and method in ("similarity", "axes"):
            transform = calibrate(np.where(fit_mask[:, None], scan_lm, np.nan), template_lm, method)
    return transform, outliers


def find_outlier_landmarks(template_points, scan_points, *, threshold: float = 6.0,
                           smoothing: float = 1.0, max_outliers: int = 3) -> list[int]:
    """Feature points whose scan position disagrees with all the others.

    Each present pair is predicted from the others by a biharmonic RBF (leave one
    out); the pair with the largest miss is removed while its miss exceeds both
    `threshold` and three times the median miss, up to `max_outliers` times.

    Parameters
    ----------
    template_points, scan_points : (k, 3) array_like
        Corresponding points (mm, scan already calibrated); NaN rows missing.
    threshold : float
        Smallest miss (mm) that counts as wrong.
    smoothing : float
        rho of the leave-one-out RBFs.
    max_outliers : int
        Most points to remove.

    Returns
    -------
    list of int, the rows judged wrong (worst first).
    """
    template = as_points(template_points, "template_points", finite=False)
    scan = as_points(scan_points, "scan_points", finite=False)
    active = np.isfinite(template).all(axis=1) & np.isfinite(scan).all(axis=1)
    outliers: list[int] = []
    while len(outliers) < max_outliers and active.sum() > 7:
        rows = np.flatnonzero(active)
        misses = np.empty(len(rows))
        for k, row in enumerate(rows):
            others = rows[rows != row]
            try:
                field = RBF(template[others], scan[others] - template[others], "biharmonic", smoothing=smoothing)
            except ValueError:
                misses[k] = 0.0
                continue
            predicted = template[row] + field(template[row][None])[0]
            misses[k] = np.linalg.norm(predicted - scan[row])
        worst = int(np.argmax(misses))
        if misses[worst] > threshold and misses[worst] > 3.0 * np.median(misses):
            outliers.append(int(rows[worst]))
            active[rows[worst]] = False
        else:
            break
    return outliers

"""The elastic face: a mesh with facial control points and its precomputed deformation
basis, which learns, blends and clones expressions as handle displacements
(``docs/elastic.md``)."""
from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.sparse as sp

from .._validation import as_faces, as_points, check_finite
from ..face.landmarks import as_landmarks
from ..face.normalise import FaceFrame, face_frame
from .cloning import clone_expressions, map_displacements
from .control_points import ElasticControlPoint, check_distinct, place_control_points, read_control_point_file
from .energy import (ElasticBasis, ElasticOptions, as_vertex_mask, default_fixed_region, energy_matrix,
                     unanchored_parts)
from .fitting import ExpressionSet, as_expressive_meshes, blend_weights, fit_expressions

__all__ = ["ElasticFace"]


def _is_definitions(control_points) -> bool:
    """Whether ``control_points`` are definitions to place (None: the shipped ones)
    rather than vertex indices."""
    if control_points is None:
        return True
    return (not isinstance(control_points, np.ndarray) and len(control_points) > 0
            and isinstance(next(iter(control_points)), ElasticControlPoint))


def _handles(vertices, faces, control_points, landmarks, names):
    """Handle vertices (k,), their names and their definitions (None for indices)."""
    if _is_definitions(control_points):
        if landmarks is None:
            raise ValueError("landmarks are needed to place the control points on the face "
                             "(or pass control_points as vertex indices)")
        if control_points is None:
            definitions, unit = read_control_point_file()
        else:
            definitions, unit = tuple(control_points), None
        handles = place_control_points(vertices, faces, landmarks, definitions, reference_facial_unit_mm=unit)
        return handles, tuple(p.name for p in definitions), definitions
    n = len(vertices)
    handles = np.asarray(control_points)
    if handles.ndim != 1 or handles.size == 0 or not np.issubdtype(handles.dtype, np.integer):
        raise ValueError("control_points must be a non-empty 1-D array of vertex indices "
                         f"(or control point definitions), got shape {handles.shape} dtype {handles.dtype}")
    handles = handles.astype(np.int64)
    if handles.min() < 0 or handles.max() >= n:
        raise ValueError(f"control_points refers to vertex indices outside [0, {n})")
    point_names = tuple(names) if names is not None else tuple(f"cp{i}" for i in range(len(handles)))
    if len(point_names) != len(handles):
        raise ValueError(f"names has {len(point_names)} entries for {len(handles)} control points")
    check_distinct(handles, point_names)
    return handles, point_names, None


def _fixed_region(vertices, faces, handles, names, fixed, landmarks, options: ElasticOptions) -> np.ndarray:
    """The mask (n,) of vertices held still: ``fixed`` or the default region, plus the
    vertices no triangle uses and, with ``unanchored="fix"``, the parts with no handle."""
    n = len(vertices)
    if fixed is None:
        if landmarks is None:
            raise ValueError("landmarks are needed for the default fixed region (or pass fixed=...)")
        mask = default_fixed_region(vertices, landmarks, options.fixed_factor)
    else:
        mask = as_vertex_mask(fixed, n, "fixed")
    inside = np.flatnonzero(mask[handles])
    if len(inside):
        listed = ", ".join(f"{names[i]!r} (vertex {handles[i]})" for i in inside[:5])
        raise ValueError(
            f"{len(inside)} control point(s) lie inside the fixed region: {listed}; "
            "shrink the fixed region (a larger fixed_factor) or move the control points")
    referenced = np.zeros(n, dtype=bool)
    referenced[faces.ravel()] = True
    mask |= ~referenced
    if mask[handles].any():
        raise ValueError("a control point is a vertex used by no triangle")
    loose = unanchored_parts(faces, n, handles, mask)
    if options.unanchored == "fix":
        return mask | (loose >= 0)
    if (loose >= 0).any():
        members = np.flatnonzero(loose == loose[loose >= 0].min())
        raise ValueError(
            f"a connected part of the mesh ({len(members)} vertices, e.g. vertex {members[0]}) "
            "has no control point and no fixed vertex, so its position is undetermined")
    return mask


def as_parameters(params, k: int, name: str = "params") -> tuple[np.ndarray, bool]:
    """Handle displacements as (e, k, 3) float64, and whether one (k, 3) was given."""
    try:
        array = np.asarray(params, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be numeric: {exc}") from None
    single = array.ndim == 2
    if single:
        array = array[None]
    if array.ndim != 3 or array.shape[1:] != (k, 3):
        raise ValueError(f"{name} must have shape ({k}, 3) or (e, {k}, 3) (one displacement per control point), "
                         f"got {np.shape(params)}")
    check_finite(array.reshape(len(array), -1), name)
    return array, single


class ElasticFace:
    """A face mesh with facial control points and a precomputed elastic deformation basis.

    Parameters
    ----------
    vertices : array_like, shape (n, 3)
        Neutral face vertices (mm).
    faces : array_like of int, shape (m, 3)
        Triangles.
    control_points : array_like of int (k,), or sequence of ElasticControlPoint, optional
        Handle vertices given directly as vertex indices, or definitions placed on this
        mesh with ``landmarks`` (:func:`~tpscore.elastic.place_control_points`). Default:
        the shipped 47 points, placed with ``landmarks``.
    landmarks : array_like, shape (22, 3), optional
        The face's Bosphorus landmarks (mm), NaN where missing. Needed for the default
        control points, the default fixed region and cloning (frame and facial unit).
    fixed : array_like, optional
        Vertices held still: a (n,) bool mask or vertex indices. Default: every vertex
        farther from the nose tip than ``options.fixed_factor`` times the
        nose-tip-to-forehead distance; pass an empty list for none. Vertices used by no
        triangle are always held still (they have no energy).
    names : sequence of str, optional
        Names of the control points when they are given as indices.
    options : ElasticOptions, optional
        The energy's weights and the fixed region's handling.

    Raises
    ------
    ValueError
        For bad arrays, a handle inside the fixed region, duplicate handles, or a part of
        the mesh with neither a handle nor a fixed vertex (unless ``options.unanchored``
        is ``"fix"``).

    Notes
    -----
    The factorisation and the basis are computed in the constructor; ``timings`` holds
    how long each took (seconds). The basis is read-only, so an ElasticFace can be used
    from several threads; :meth:`fit` and cloning set :attr:`expressions`.
    """

    def __init__(self, vertices, faces, control_points=None, *, landmarks=None, fixed=None,
                 names: Sequence[str] | None = None, options: ElasticOptions = ElasticOptions()):
        if not isinstance(options, ElasticOptions):
            raise ValueError(f"options must be an ElasticOptions, got {type(options).__name__}")
        vertices = as_points(vertices, "vertices", allow_empty=False).copy()
        faces = as_faces(faces, len(vertices)).copy()
        if len(faces) == 0:
            raise ValueError("faces is empty; the deformation needs a triangle mesh")
        self._landmarks = None if landmarks is None else as_landmarks(landmarks)
        self._frame = None if self._landmarks is None else face_frame(self._landmarks)
        handles, self._names, self._definitions = _handles(vertices, faces, control_points, self._landmarks, names)
        self._fixed = _fixed_region(vertices, faces, handles, self._names, fixed, self._landmarks, options)
        self._vertices, self._faces, self._handles, self._options = vertices, faces, handles, options
        self._basis = ElasticBasis(self.energy_matrix(), handles, self._fixed)
        self._qr = None
        self.expressions: ExpressionSet | None = None
        for array in (self._vertices, self._faces, self._handles, self._fixed, self._landmarks):
            if array is not None:
                array.setflags(write=False)

    # ------------------------------------------------------------------ properties
    @property
    def vertices(self) -> np.ndarray:
        """Neutral vertices (n, 3), mm, read-only."""
        return self._vertices

    @property
    def faces(self) -> np.ndarray:
        """Triangles (m, 3) int64, read-only."""
        return self._faces

    @property
    def handles(self) -> np.ndarray:
        """Vertex index of each control point (k,), read-only."""
        return self._handles

    @property
    def control_point_names(self) -> tuple[str, ...]:
        """Name of each control point (k,)."""
        return self._names

    @property
    def control_points(self) -> tuple[ElasticControlPoint, ...] | None:
        """The definitions the control points were placed from (None when they were
        given as vertex indices)."""
        return self._definitions

    @property
    def control_point_positions(self) -> np.ndarray:
        """Neutral positions of the control points (k, 3), mm."""
        return self._vertices[self._handles]

    @property
    def fixed(self) -> np.ndarray:
        """Mask (n,) of the vertices held still, read-only."""
        return self._fixed

    @property
    def basis(self) -> np.ndarray:
        """The deformation basis (n, k): column j is the displacement field (per unit) of
        handle j moved alone; rows of handles are the identity, fixed rows are 0."""
        return self._basis.matrix

    @property
    def landmarks(self) -> np.ndarray | None:
        """The landmarks (22, 3) the face was given, read-only."""
        return self._landmarks

    @property
    def frame(self) -> FaceFrame | None:
        """The face frame (needs landmarks)."""
        return self._frame

    @property
    def options(self) -> ElasticOptions:
        return self._options

    @property
    def timings(self) -> dict[str, float]:
        """Seconds spent factorising the free block and precomputing the basis."""
        return dict(self._basis.timings)

    def __repr__(self) -> str:
        return (f"ElasticFace(vertices={len(self._vertices)}, control_points={len(self._handles)}, "
                f"fixed={int(self._fixed.sum())}, stretching={self._options.stretching:g}, "
                f"bending={self._options.bending:g})")

    def energy_matrix(self) -> sp.csr_matrix:
        """The (n, n) energy operator -k_s L + k_b L M^-1 L (symmetric positive semi-definite)."""
        return energy_matrix(self._vertices, self._faces, self._options.stretching, self._options.bending)

    # ------------------------------------------------------------------ deformation
    def displacement(self, params) -> np.ndarray:
        """Per-vertex displacement ``basis @ params``: (n, 3) for params (k, 3), or
        (e, n, 3) for (e, k, 3); mm."""
        array, single = as_parameters(params, len(self._handles))
        result = np.einsum("nk,ekd->end", self.basis, array, optimize=True)
        return result[0] if single else result

    def deform(self, params) -> np.ndarray:
        """Deformed vertices ``vertices + basis @ params``: (n, 3) or (e, n, 3), mm.

        Parameters
        ----------
        params : array_like, shape (k, 3) or (e, k, 3)
            Displacement of each control point (mm).
        """
        return self._vertices + self.displacement(params)

    def solve_direct(self, params) -> np.ndarray:
        """Deformed vertices (n, 3) from a fresh solve with the factor (no basis).

        The same result as :meth:`deform` up to rounding; it checks the basis, and
        serves when only one deformation of a face is ever needed.
        """
        array, single = as_parameters(params, len(self._handles))
        if not single:
            raise ValueError("solve_direct takes one expression's params of shape (k, 3)")
        return self._vertices + self._basis.solve(array[0])

    # --------------------------------------------------------------------- learning
    def fit(self, expressive_vertices, names: Sequence[str] | None = None, *, faces=None) -> ExpressionSet:
        """Learn the control-point displacements of example expressions by least squares.

        For each expression, params = argmin || basis @ params - (expressive - neutral) ||
        over all vertices, solved with the QR factorisation of the basis.

        Parameters
        ----------
        expressive_vertices : array_like, shape (e, n, 3) or (n, 3)
            Expressive meshes with this face's connectivity (vertex i of each is vertex i
            of the neutral), mm.
        names : sequence of str, optional
            Expression names (default "expr0", ...).
        faces : array_like, optional
            The expressive meshes' triangles; when given they must equal this face's
            triangles, which guards against meshes of another connectivity.

        Returns
        -------
        ExpressionSet
            Parameters (e, k, 3) with per-expression reconstruction errors; also stored
            as :attr:`expressions`.
        """
        examples = as_expressive_meshes(expressive_vertices, self._faces, len(self._vertices), faces)
        if self._qr is None:
            # Reduced QR of the (n, k) basis; its rows of handles are the identity, so it
            # has full column rank and R is invertible.
            self._qr = np.linalg.qr(self.basis)
        self.expressions = fit_expressions(self.basis, self._qr, examples - self._vertices, names)
        return self.expressions

    def _expressions(self, expressions: ExpressionSet | None) -> ExpressionSet:
        expressions = self.expressions if expressions is None else expressions
        if expressions is None:
            raise ValueError("this face has no learned expressions: call fit() first (or pass expressions=)")
        if expressions.parameters.shape[1] != len(self._handles):
            raise ValueError(f"expressions have {expressions.parameters.shape[1]} control points; "
                             f"this face has {len(self._handles)}")
        return expressions

    def blend_parameters(self, weights, expressions: ExpressionSet | None = None) -> np.ndarray:
        """Control-point displacements (k, 3) of a blend: sum_e weights[e] * params[e]."""
        expressions = self._expressions(expressions)
        return np.tensordot(blend_weights(weights, expressions), expressions.parameters, axes=1)

    def blend(self, weights, expressions: ExpressionSet | None = None) -> np.ndarray:
        """A new expression from weights over learned ones, blended at the control points.

        Parameters
        ----------
        weights : array_like (e,) or mapping name -> weight
            One weight per learned expression (any real numbers; 0..1 is typical).
        expressions : ExpressionSet, optional
            Default: :attr:`expressions`.

        Returns
        -------
        ndarray, shape (n, 3)
            The deformed vertices (mm).
        """
        return self.deform(self.blend_parameters(weights, expressions))

    def expression(self, name: str, magnitude: float = 1.0) -> np.ndarray:
        """Vertices (n, 3) of one learned expression at a magnitude."""
        expressions = self._expressions(None)
        return self.deform(expressions.parameters[expressions.index(name)] * float(magnitude))

    # ---------------------------------------------------------------------- cloning
    def clone_to(self, target, expressions: ExpressionSet | None = None, *, target_landmarks=None,
                 options: ElasticOptions | None = None) -> "ElasticFace":
        """Clone the learned expressions onto another face, of any mesh structure.

        The target's control points are this face's control points carried over by the
        landmark TPS and snapped to the target (unless ``target`` is an ElasticFace, whose
        own control points, in the same order, are used). Each displacement is carried
        into the target's frame and scaled by the ratio of the facial units
        (:func:`~tpscore.elastic.cloning.map_displacements`); the target's own basis
        spreads it.

        Parameters
        ----------
        target : ElasticFace or (vertices, faces)
            The target face. A (vertices, faces) pair needs ``target_landmarks``; build
            an ElasticFace yourself for a target with its own fixed region.
        expressions : ExpressionSet, optional
            Default: :attr:`expressions`.
        target_landmarks : array_like, shape (22, 3), optional
            The target's landmarks (mm) when ``target`` is a mesh.
        options : ElasticOptions, optional
            The options of the target's ElasticFace when ``target`` is a mesh (default:
            the defaults).

        Returns
        -------
        ElasticFace
            The target face with :attr:`expressions` holding the cloned parameters (a
            shallow copy when ``target`` was an ElasticFace; the original is unchanged).
        """
        return clone_expressions(self, target, self._expressions(expressions), target_landmarks=target_landmarks,
                                 options=options)

    def map_displacements(self, displacements, target_frame: FaceFrame) -> np.ndarray:
        """Displacements (..., 3) of this face, rotated into ``target_frame`` and scaled by
        the ratio of facial units (target / this)."""
        return map_displacements(displacements, self._frame, target_frame)

    # ---------------------------------------------------------------------- storage
    def storage(self, expressions: ExpressionSet | None = None) -> dict[str, float]:
        """Numbers stored for an expression set, in float64 values.

        Returns
        -------
        dict
            ``parameters`` (e * k * 3), ``basis`` (n * k), ``per_vertex`` (e * n * 3, the
            displacements of every vertex), ``ratio`` ((parameters + basis) / per_vertex,
            the method's storage ratio) and ``ratio_parameters_only`` (parameters /
            per_vertex, when the basis is recomputed from the neutral mesh instead of
            stored).
        """
        expressions = self._expressions(expressions)
        e, k, n = len(expressions), len(self._handles), len(self._vertices)
        parameters, basis, per_vertex = e * k * 3, n * k, e * n * 3
        return {"expressions": e, "control_points": k, "vertices": n,
                "parameters": parameters, "basis": basis, "per_vertex": per_vertex,
                "ratio": (parameters + basis) / per_vertex,
                "ratio_parameters_only": parameters / per_vertex}

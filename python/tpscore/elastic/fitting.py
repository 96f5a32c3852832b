"""Expressions as handle displacements: learned from example meshes by least squares
and blended by weights, so that a whole expression set is a few numbers per handle."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import scipy.linalg

from .._validation import check_finite

__all__ = ["ExpressionSet", "fit_expressions"]


@dataclass(frozen=True)
class ExpressionSet:
    """Learned (or cloned) expression parameters: handle displacements per expression.

    Attributes
    ----------
    names : tuple of str
        One per expression.
    parameters : ndarray, shape (e, k, 3)
        Handle displacements (mm), in the order of the face's control points.
    rms_mm : ndarray, shape (e,) or None
        Root-mean-square per-vertex error of the reconstruction ``basis @ parameters``
        against the example expression (mm), when fitted.
    max_mm : ndarray, shape (e,) or None
        Largest per-vertex error (mm), when fitted.
    motion_rms_mm : ndarray, shape (e,) or None
        RMS per-vertex motion of the example itself (mm): rms_mm / motion_rms_mm is the
        fraction of the motion the model misses.
    """

    names: tuple[str, ...]
    parameters: np.ndarray
    rms_mm: np.ndarray | None = None
    max_mm: np.ndarray | None = None
    motion_rms_mm: np.ndarray | None = None

    def __post_init__(self):
        parameters = np.asarray(self.parameters, dtype=np.float64)
        if parameters.ndim != 3 or parameters.shape[2] != 3:
            raise ValueError(f"parameters must have shape (e, k, 3), got {parameters.shape}")
        check_finite(parameters.reshape(len(parameters), -1), "parameters")
        names = tuple(str(n) for n in self.names)
        if len(names) != len(parameters):
            raise ValueError(f"names has {len(names)} entries for {len(parameters)} expressions")
        parameters = parameters.copy()
        parameters.setflags(write=False)
        object.__setattr__(self, "parameters", parameters)
        object.__setattr__(self, "names", names)

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """Position of the expression called ``name``."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueError(f"unknown expression {name!r}; known: {', '.join(self.names)}") from None


def as_expressive_meshes(expressive_vertices, neutral_faces: np.ndarray, n: int, faces=None) -> np.ndarray:
    """Expressive meshes as an (e, n, 3) float64 array, checked to share the neutral
    mesh's connectivity (n vertices, and ``faces`` equal to ``neutral_faces`` if given)."""
    try:
        examples = np.asarray(expressive_vertices, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"expressive_vertices must be numeric: {exc}") from None
    if examples.ndim == 2:
        examples = examples[None]
    if examples.ndim != 3 or examples.shape[2] != 3:
        raise ValueError(f"expressive_vertices must have shape (e, {n}, 3) or ({n}, 3), got {np.shape(expressive_vertices)}")
    if examples.shape[1] != n:
        raise ValueError(
            f"expressive_vertices has {examples.shape[1]} vertices per mesh but the neutral face has {n}: "
            "the expressions must share the neutral mesh's connectivity")
    if faces is not None:
        other = np.asarray(faces)
        if other.shape != neutral_faces.shape or not np.array_equal(other, neutral_faces):
            raise ValueError("faces of the expressive meshes differ from the neutral face's: "
                             "the expressions must share the neutral mesh's connectivity")
    check_finite(examples.reshape(len(examples), -1), "expressive_vertices")
    if len(examples) == 0:
        raise ValueError("expressive_vertices holds no expression")
    return examples


def fit_expressions(basis: np.ndarray, qr: tuple[np.ndarray, np.ndarray], motion: np.ndarray,
                    names: Sequence[str] | None = None) -> ExpressionSet:
    """Handle displacements that best explain each example's motion.

    Parameters
    ----------
    basis : ndarray, shape (n, k)
        The deformation basis.
    qr : (ndarray (n, k), ndarray (k, k))
        Its reduced QR factorisation.
    motion : ndarray, shape (e, n, 3)
        Each example's displacement from the neutral mesh (mm).
    names : sequence of str, optional
        Expression names (default "expr0", ...).

    Returns
    -------
    ExpressionSet
        argmin || basis @ params - motion || per expression, with its errors.
    """
    e, n, k = len(motion), len(basis), basis.shape[1]
    expression_names = tuple(names) if names is not None else tuple(f"expr{i}" for i in range(e))
    if len(expression_names) != e:
        raise ValueError(f"names has {len(expression_names)} entries for {e} expressions")
    q, r = qr
    stacked = motion.transpose(1, 0, 2).reshape(n, 3 * e)
    solution = scipy.linalg.solve_triangular(r, q.T @ stacked)
    params = solution.reshape(k, e, 3).transpose(1, 0, 2)
    residual = np.einsum("nk,ekd->end", basis, params, optimize=True) - motion
    error = np.linalg.norm(residual, axis=2)
    return ExpressionSet(
        names=expression_names, parameters=params,
        rms_mm=np.sqrt((error ** 2).mean(axis=1)), max_mm=error.max(axis=1),
        motion_rms_mm=np.sqrt((motion ** 2).sum(axis=2).mean(axis=1)))


def blend_weights(weights, expressions: ExpressionSet) -> np.ndarray:
    """One weight per expression (e,), from an array or a name -> weight mapping
    (unnamed expressions weigh 0)."""
    if isinstance(weights, Mapping):
        vector = np.zeros(len(expressions))
        for name, w in weights.items():
            vector[expressions.index(name)] = float(w)
    else:
        try:
            vector = np.asarray(weights, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"weights must be numeric: {exc}") from None
    if vector.shape != (len(expressions),):
        raise ValueError(f"weights must have shape ({len(expressions)},) (one per expression) or be a "
                         f"name -> weight mapping, got {np.shape(weights)}")
    check_finite(vector, "weights")
    return vector

"""Reference dense RBF / thin-plate spline: the textbook system, solved as written.

Same kernels and conventions as :mod:`tpscore.rbf` (phi(r) for "tps" is r^2 ln r^2,
the affine part is [1 x y z], smoothing enters as ``K + sign * smoothing * I``), but
with no centring or scaling, no chunking and no validation: the full saddle-point
system in the original coordinates goes to ``np.linalg.solve``, and evaluation forms
the dense (m, n, 3) difference array. Memory grows as 32 * m * n bytes or more.
"""
from __future__ import annotations

import numpy as np

__all__ = ["SMOOTHING_SIGN", "kernel", "kernel_matrix", "fit", "evaluate",
           "evaluation_matrix", "bending_energy"]

#: The sign that makes sign * K conditionally positive definite, per kernel.
SMOOTHING_SIGN = {"tps": 1.0, "biharmonic": -1.0, "triharmonic": 1.0,
                  "multiquadric": -1.0, "gaussian": 1.0}


def kernel(name: str, r: np.ndarray, epsilon: float | None = None) -> np.ndarray:
    """phi(r) for distances r (mm)."""
    r = np.asarray(r, dtype=np.float64)
    if name == "tps":
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(r > 0, r**2 * np.log(r**2), 0.0)
    if name == "biharmonic":
        return r
    if name == "triharmonic":
        return r**3
    if name == "multiquadric":
        return np.sqrt(1.0 + (epsilon * r) ** 2)
    if name == "gaussian":
        return np.exp(-((epsilon * r) ** 2))
    raise ValueError(f"unknown kernel {name!r}")


def kernel_matrix(name: str, points: np.ndarray, centres: np.ndarray,
                  epsilon: float | None = None) -> np.ndarray:
    """(m, n) matrix phi(|points_i - centres_j|)."""
    differences = points[:, None, :] - centres[None, :, :]
    return kernel(name, np.sqrt(np.sum(differences**2, axis=2)), epsilon)


def _polynomial(points: np.ndarray) -> np.ndarray:
    return np.hstack([np.ones((len(points), 1)), points])


def fit(centres, values, name: str = "tps", smoothing: float = 0.0,
        epsilon: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Solve [[K + sign*smoothing*I, P], [P^T, 0]] [W; A] = [values; 0].

    Returns weights W (n, k) and affine A (4, k).
    """
    centres = np.asarray(centres, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64).reshape(len(centres), -1)
    n = len(centres)
    matrix = np.zeros((n + 4, n + 4))
    matrix[:n, :n] = kernel_matrix(name, centres, centres, epsilon)
    matrix[:n, :n] += SMOOTHING_SIGN[name] * smoothing * np.eye(n)
    matrix[:n, n:] = _polynomial(centres)
    matrix[n:, :n] = _polynomial(centres).T
    right = np.vstack([values, np.zeros((4, values.shape[1]))])
    solution = np.linalg.solve(matrix, right)
    return solution[:n], solution[n:]


def evaluation_matrix(points, centres, name: str = "tps",
                      epsilon: float | None = None) -> np.ndarray:
    """(m, n + 4) matrix [phi(|x - p_j|) | 1 x y z]."""
    points = np.asarray(points, dtype=np.float64)
    centres = np.asarray(centres, dtype=np.float64)
    return np.hstack([kernel_matrix(name, points, centres, epsilon), _polynomial(points)])


def evaluate(points, centres, weights, affine, name: str = "tps",
             epsilon: float | None = None) -> np.ndarray:
    """f(points) = [1 x y z] A + sum_j W_j phi(|x - p_j|), shape (m, k)."""
    return evaluation_matrix(points, centres, name, epsilon) @ np.vstack([weights, affine])


def bending_energy(centres, weights, name: str = "tps", epsilon: float | None = None) -> float:
    """trace(W^T K W) with K the centres' kernel matrix (no smoothing)."""
    centres = np.asarray(centres, dtype=np.float64)
    matrix = kernel_matrix(name, centres, centres, epsilon)
    return float(np.trace(weights.T @ matrix @ weights))

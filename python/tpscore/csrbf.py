"""Compactly supported radial basis functions (CSRBF) with optional local quadrics.

A CSRBF field maps points near a set of centres to values (typically 3D
displacements, mm) with Wendland's kernel, so each centre only influences points
within the support and the fit is a sparse linear system:

    f(x) = sum_j (g_j(x) + c_j) phi_sigma(|x - p_j|),
    phi_sigma(d) = phi(d / sigma),  phi(r) = (1 - r)^4_+ (4 r + 1).

Without the quadric g_j = 0. With it, g_j is a local quadratic model of the values
around p_j in the centre's tangent frame, and the c_j correct what the local models
miss. This is the vector-valued form of the implicit-surface CSRBF of Ohtake,
Belyaev and Seidel ("3D scattered data approximation with adaptive compactly
supported radial basis functions", 2004): every value column is fitted
independently, with the same sparse matrix.
"""
from __future__ import annotations

import numbers

import numpy as np

from . import _core
from .spatial import _pairs_beyond
from ._validation import (Immutable, MAX_SPARSE_ENTRIES, as_array, as_flag, as_points, as_positive, as_values,
                          check_result_size, gib)

__all__ = ["CSRBF", "ConvergenceError", "wendland"]

#: The most stored entries of a CSRBF matrix (pairs of centres within the support, the
#: diagonal included): 2**28, whose float64 values alone take 2 GiB, the budget of a
#: dense fit's matrix. Counted before the matrix is assembled.
MAX_CSRBF_NONZEROS = MAX_SPARSE_ENTRIES

_PRECONDITIONERS = {"diagonal": _core.CSRBFPreconditioner.diagonal, "ilu": _core.CSRBFPreconditioner.ilu}


class ConvergenceError(RuntimeError):
    """The iterative solve of a fit did not reach its tolerance."""


def wendland(r):
    """Wendland's C2 function phi(r) = (1 - r)^4 (4 r + 1) for r < 1, else 0.

    Parameters
    ----------
    r : array_like
        Distances divided by the support (dimensionless), >= 0.

    Returns
    -------
    ndarray
        phi(r), same shape as ``r``; phi(0) = 1, phi(r >= 1) = 0.
    """
    r = as_array(r, "r")
    return np.where(r < 1, (1 - r) ** 4 * (4 * r + 1), 0.0)


class CSRBF(Immutable):
    """A field fitted to values at centres with compactly supported Wendland RBFs.

    Fitting (all in the compiled core, threaded where it pays):

    1. the pairs of centres closer than ``support``, from a kd-tree;
    2. with ``quadric=True``, per centre p_j: a unit normal (``normals``, or the
       direction of least spread of the Wendland-weighted centres within the support:
       weighted PCA), a tangent frame (u, v) orthogonal to it, and the
       Wendland-weighted least-squares fit of
       g_j(x) = a + b u + c v + A u^2 + 2 B u v + C v^2 to the values of the centres
       within its support, per value column. A quadratic needs 6 such centres (p_j
       included) that determine it (no rank deficiency: pivot above 1e-6 of the
       largest); otherwise the fit falls back to linear (3 centres), then to a
       constant (the weighted mean). :attr:`quadric_orders` records which;
    3. the sparse matrix Phi_ij = phi_sigma(|p_i - p_j|) + smoothing delta_ij and the
       right-hand sides values_i - sum_j g_j(p_i) phi_sigma(|p_i - p_j|);
    4. Eigen's BiCGSTAB per value column (columns in parallel), with a Jacobi
       (``"diagonal"``) or incomplete-LU (``"ilu"``) preconditioner, until the true
       relative residual |b - Phi c| / |b| is at most ``tolerance``.

    Parameters
    ----------
    centres : array_like, shape (n, 3)
        Centre positions p_j, mm; n >= 1, finite, no two closer than 1e-9 * support.
    values : array_like, shape (n,) or (n, k)
        Values at the centres (e.g. displacements, mm).
    support : float
        The support radius sigma, mm, > 0: each centre influences points closer
        than this. Choose it so that each centre has some tens of neighbours; the
        matrix may hold at most :data:`MAX_CSRBF_NONZEROS` pairs of centres within it.
    normals : array_like, shape (n, 3), optional
        Surface normals at the centres for the quadric's tangent frames (need not be
        unit length, must be nonzero). Estimated by weighted PCA when omitted. Only
        used with ``quadric=True``.
    quadric : bool, default False
        Fit the local models g_j (better reproduction of smooth fields between the
        centres, at about twice the fitting cost).
    smoothing : float, default 0
        Added to the diagonal of Phi, >= 0. 0 interpolates (f(p_i) = values_i up to
        the tolerance); larger values trade exactness for robustness to noise:
        f(p_i) + smoothing * c_i = values_i.
    preconditioner : {"ilu", "diagonal"}, default "ilu"
        "ilu" (incomplete LU with threshold) costs a factorisation but needs only a
        few iterations and copes with clustered centres; "diagonal" (Jacobi) is free
        to set up but can need hundreds of iterations.
    tolerance : float, default 1e-10
        Relative residual to reach, > 0.
    max_iterations : int, default 1000
        BiCGSTAB iteration budget per value column, >= 1.

    Raises
    ------
    ValueError
        Invalid arguments (the message names the argument), including duplicate
        centres (naming the two rows) and a support that puts more than
        :data:`MAX_CSRBF_NONZEROS` pairs of centres in the matrix (counted before it is
        assembled).
    ConvergenceError
        A value column did not reach the tolerance within ``max_iterations`` (the
        message gives the residuals). A field that missed its tolerance is never
        returned silently; raise ``max_iterations``, loosen ``tolerance``, use
        ``preconditioner="ilu"`` or add ``smoothing``.

    Notes
    -----
    Outside the union of the centres' supports the field is 0. Fitted objects are
    immutable; evaluation releases the GIL, so several threads may evaluate one field
    at once.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> centres = rng.uniform(-50, 50, size=(500, 3))
    >>> field = CSRBF(centres, np.sin(centres / 20), support=30.0)
    >>> np.allclose(field(centres), np.sin(centres / 20), atol=1e-7)
    True
    """

    def __init__(self, centres, values, support, *, normals=None, quadric: bool = False,
                 smoothing: float = 0.0, preconditioner: str = "ilu", tolerance: float = 1e-10,
                 max_iterations: int = 1000):
        centres = as_points(centres, "centres", allow_empty=False)
        n = len(centres)
        self._one_dimensional = np.ndim(values) == 1
        values = as_values(values, n, "values")
        if values.shape[1] == 0:
            raise ValueError("values must have at least one column, got shape (n, 0)")
        support = as_positive(support, "support")
        smoothing = as_positive(smoothing, "smoothing", allow_zero=True)
        tolerance = as_positive(tolerance, "tolerance")
        as_flag(quadric, "quadric")
        if preconditioner not in _PRECONDITIONERS:
            raise ValueError(
                f"preconditioner must be one of {sorted(_PRECONDITIONERS)}, got {preconditioner!r}")
        if (isinstance(max_iterations, (bool, np.bool_)) or not isinstance(max_iterations, numbers.Integral)
                or max_iterations < 1):
            raise ValueError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
        if normals is None:
            normals_array = np.zeros((0, 3))
        else:
            normals_array = as_points(normals, "normals")
            if len(normals_array) != n:
                raise ValueError(f"normals must have shape ({n}, 3) like centres, got {normals_array.shape}")
            lengths = np.linalg.norm(normals_array, axis=1)
            if np.any(lengths == 0):
                raise ValueError(f"normals has zero-length rows (first at row {np.flatnonzero(lengths == 0)[0]})")

        # the inputs, as given, for pickling (the fit is deterministic: a refit gives the
        # same coefficients to the bit with the same build)
        self._inputs = (np.array(centres), np.array(values[:, 0] if self._one_dimensional else values),
                        None if normals is None else np.array(normals_array))
        self._support = support
        self._quadric = bool(quadric)
        self._smoothing = smoothing
        self._preconditioner = preconditioner
        self._tolerance = tolerance
        self._max_iterations = int(max_iterations)
        _check_nonzeros(centres, support)
        self._fit = _core.CSRBF(centres, values, normals_array, support, smoothing, bool(quadric),
                                _PRECONDITIONERS[preconditioner], tolerance, int(max_iterations))
        self._coefficients = self._fit.coefficients
        self._iterations = self._fit.iterations.view(np.int64)
        self._residuals = self._fit.residuals
        for array in (self._coefficients, self._iterations, self._residuals):
            array.flags.writeable = False
        converged = self._fit.converged
        if not converged.all():
            failed = np.flatnonzero(~converged)
            raise ConvergenceError(
                f"CSRBF solve did not converge for value column(s) {failed.tolist()}: relative "
                f"residuals {self._residuals[failed].tolist()} after {self._iterations[failed].tolist()} "
                f"iterations (tolerance {tolerance:g}, max_iterations {max_iterations}); raise "
                f"max_iterations, loosen tolerance, use preconditioner='ilu' or add smoothing")

    def __reduce__(self):
        centres, values, normals = self._inputs
        return _refit, (centres, values, self._support, normals, self._quadric, self._smoothing,
                        self._preconditioner, self._tolerance, self._max_iterations)

    def __call__(self, points) -> np.ndarray:
        """Evaluate the field.

        Parameters
        ----------
        points : array_like, shape (m, 3)
            Query points, mm.

        Returns
        -------
        ndarray, shape (m, k), or (m,) if the values were 1-D
            The field; 0 where no centre is within the support.

        Raises
        ------
        ValueError
            Bad points, or an (m, k) result above 2 GiB (refused before the points are
            converted: evaluate in chunks of rows).
        """
        check_result_size(points, self._coefficients.shape[1])
        points = as_points(points, "points")
        result = self._fit.evaluate(points)
        return result[:, 0] if self._one_dimensional else result

    @property
    def support(self) -> float:
        """The support radius sigma, mm."""
        return self._support

    @property
    def coefficients(self) -> np.ndarray:
        """(n, k) the c_j (read-only)."""
        return self._coefficients

    @property
    def iterations(self) -> np.ndarray:
        """(k,) BiCGSTAB iterations per value column (read-only)."""
        return self._iterations

    @property
    def residuals(self) -> np.ndarray:
        """(k,) true relative residual |b - Phi c| / |b| per value column (read-only)."""
        return self._residuals

    @property
    def nnz(self) -> int:
        """Stored entries of Phi (pairs of centres within the support, the diagonal included)."""
        return int(self._fit.nnz)

    @property
    def quadric_orders(self) -> np.ndarray | None:
        """(n,) order of each local model (2 quadratic, 1 linear, 0 constant), or None
        without the quadric."""
        return self._fit.quadric_orders.view(np.int64) if self._quadric else None

    @property
    def normals(self) -> np.ndarray | None:
        """(n, 3) unit normals of the quadric's tangent frames (given or estimated; the
        sign of an estimated normal is arbitrary), or None without the quadric."""
        return self._fit.normals if self._quadric else None

    def __repr__(self) -> str:
        return (f"CSRBF(n={len(self._coefficients)}, k={self._coefficients.shape[1]}, "
                f"support={self._support:g}, quadric={self._quadric}, nnz={self.nnz})")


def _check_nonzeros(centres: np.ndarray, support: float) -> None:
    """Refuse, before the matrix is assembled, a support that gives it more than
    MAX_CSRBF_NONZEROS entries: the pairs within the support are counted on a kd-tree
    (only when n^2 could pass the limit: up to 16,384 centres it cannot)."""
    n = len(centres)
    if n * n <= MAX_CSRBF_NONZEROS:
        return
    nonzeros = _pairs_beyond(_core.KDTree(centres, 16), centres, support, 0, MAX_CSRBF_NONZEROS)
    if nonzeros is not None:
        raise ValueError(
            f"support: with support = {support:g} mm the {n:,} centres have {nonzeros:,} pairs within "
            f"the support (about {nonzeros // n:,} neighbours each), so the CSRBF matrix would have "
            f"{nonzeros:,} nonzeros ({gib(8.0 * nonzeros)} of values alone), more than the limit of "
            f"{MAX_CSRBF_NONZEROS:,} ({gib(8.0 * MAX_CSRBF_NONZEROS)}); use a smaller support "
            "(some tens of neighbours per centre)")


def _refit(centres, values, support, normals, quadric, smoothing, preconditioner, tolerance, max_iterations):
    """A fitted CSRBF from its inputs: what unpickling calls."""
    return CSRBF(centres, values, support, normals=normals, quadric=quadric, smoothing=smoothing,
                 preconditioner=preconditioner, tolerance=tolerance, max_iterations=max_iterations)

"""Sparse direct solve: factorise a symmetric positive-definite matrix once, solve many times.

The elastic face model solves the same bi-Laplacian system for one right-hand side
per control point; factorising once and reusing the factor is what makes its basis
cheap. :class:`SparseCholesky` wraps the compiled LDL^T factorisation (Eigen's
SimplicialLDLT with an approximate-minimum-degree ordering).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from . import _core
from ._validation import check_finite

__all__ = ["SparseCholesky"]

# A pivot of D at or below this fraction of the largest pivot means the matrix is
# singular or indefinite to working precision: with ~1e-16 rounding per operation, a
# well-posed SPD system keeps its smallest pivot many orders above this.
_PIVOT_TOLERANCE = 1e-13


def _as_symmetric_csc_lower(matrix, name: str, symmetry_tolerance: float):
    """The lower triangle of a validated square, symmetric, finite sparse matrix as CSC."""
    if not sp.issparse(matrix):
        try:
            dense = np.asarray(matrix, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name} must be a scipy.sparse matrix or a numeric 2-D array: {exc}") from None
        if dense.ndim != 2:
            raise ValueError(f"{name} must be 2-D, got shape {dense.shape}")
        matrix = sp.csc_matrix(dense)
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1]:
        raise ValueError(f"{name} must be square, got shape {matrix.shape}")
    if not np.issubdtype(matrix.dtype, np.number) or np.issubdtype(matrix.dtype, np.complexfloating):
        raise ValueError(f"{name} must hold real numbers, got dtype {matrix.dtype}")
    csc = sp.csc_matrix(matrix, dtype=np.float64, copy=True)
    csc.sum_duplicates()
    csc.eliminate_zeros()
    if csc.nnz and not np.isfinite(csc.data).all():
        raise ValueError(f"{name} contains NaN or infinite entries")
    scale = float(np.abs(csc.data).max()) if csc.nnz else 0.0
    asymmetry = abs(csc - csc.T)
    worst = float(asymmetry.max()) if asymmetry.nnz else 0.0
    if worst > symmetry_tolerance * scale:
        raise ValueError(
            f"{name} must be symmetric: |A - A^T| reaches {worst:.3g} "
            f"(largest entry {scale:.3g}, tolerance {symmetry_tolerance:g} relative)")
    lower = sp.tril(csc, format="csc")
    lower.sort_indices()
    if lower.nnz >= 2**31 - 1:
        raise ValueError(f"{name} has {lower.nnz} nonzeros in its lower triangle; the limit is 2^31 - 1")
    return lower


class SparseCholesky:
    """A sparse symmetric positive-definite matrix, factorised once for repeated solves.

    The factorisation is P A P^T = L D L^T (a square-root-free Cholesky) with an
    approximate-minimum-degree ordering P that keeps the factor sparse. Only the lower
    triangle of ``matrix`` is used once symmetry has been checked. The object is
    immutable; :meth:`solve` releases the GIL and may be called from several threads.

    Parameters
    ----------
    matrix : scipy.sparse matrix or array_like, shape (n, n)
        Real, finite, symmetric (to ``symmetry_tolerance`` relative to its largest
        entry) and positive definite.
    symmetry_tolerance : float, default 1e-10
        Largest allowed |A_ij - A_ji| as a fraction of max |A_ij|.

    Raises
    ------
    ValueError
        If the matrix is not square, not symmetric, not finite, or not positive definite
        (a pivot of D at or below 1e-13 times the largest: singular or indefinite).

    Examples
    --------
    >>> import scipy.sparse as sp
    >>> A = sp.diags([[-1.0] * 3, [2.0] * 4, [-1.0] * 3], [-1, 0, 1])
    >>> SparseCholesky(A).solve([1.0, 0.0, 0.0, 1.0])
    array([1., 1., 1., 1.])
    """

    def __init__(self, matrix, *, symmetry_tolerance: float = 1e-10):
        lower = _as_symmetric_csc_lower(matrix, "matrix", float(symmetry_tolerance))
        self._n = lower.shape[0]
        self._factor = _core.SparseCholesky(
            self._n,
            np.ascontiguousarray(lower.indptr, dtype=np.int64),
            np.ascontiguousarray(lower.indices, dtype=np.int64),
            np.ascontiguousarray(lower.data, dtype=np.float64),
            _PIVOT_TOLERANCE,
        )

    @property
    def n(self) -> int:
        """Order of the matrix."""
        return self._n

    @property
    def factor_nonzeros(self) -> int:
        """Nonzeros in the strictly lower part of the factor L (the fill-in)."""
        return int(self._factor.factor_nonzeros)

    @property
    def pivot_range(self) -> tuple[float, float]:
        """(smallest, largest) pivot of D; their ratio bounds the conditioning from below."""
        return float(self._factor.min_pivot), float(self._factor.max_pivot)

    def __repr__(self) -> str:
        return f"SparseCholesky(n={self._n}, factor_nonzeros={self.factor_nonzeros})"

    def solve(self, rhs) -> np.ndarray:
        """Solve A x = b.

        Parameters
        ----------
        rhs : array_like, shape (n,) or (n, k)
            Right-hand side(s), finite. Columns are solved in parallel.

        Returns
        -------
        ndarray, shape (n,) or (n, k)
            The solution, in the shape of ``rhs``, C-contiguous float64.
        """
        try:
            array = np.asarray(rhs, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"rhs must be numeric: {exc}") from None
        vector = array.ndim == 1
        if vector:
            array = array[:, None]
        if array.ndim != 2 or array.shape[0] != self._n:
            raise ValueError(f"rhs must have shape ({self._n},) or ({self._n}, k), got {np.shape(rhs)}")
        check_finite(array, "rhs")
        if array.shape[1] == 0 or self._n == 0:
            solution = np.zeros(array.shape)
        else:
            # Fortran order lets the core read each column in place.
            solution = np.ascontiguousarray(self._factor.solve(np.asfortranarray(array)))
        return solution[:, 0] if vector else solution

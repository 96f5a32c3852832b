"""Sparse direct solve: factorise a symmetric positive-definite matrix once, solve many times.

The elastic face model solves the same bi-Laplacian system for one right-hand side
per control point; factorising once and reusing the factor is what makes its basis
cheap. :class:`SparseCholesky` wraps the compiled LDL^T factorisation (Eigen's
SimplicialLDLT with an approximate-minimum-degree ordering). :class:`PatternCholesky`
factorises a sequence of matrices that share one sparsity pattern, analysing the
pattern once (the iterations of the dense registration in :mod:`tpscore.expression.registration`).
"""
from __future__ import annotations

from functools import partial

import numpy as np
import scipy.sparse as sp

from . import _core
from ._threads import as_workers
from ._validation import Immutable, as_array, as_positive, check_finite

__all__ = ["PatternCholesky", "SparseCholesky", "grid_nested_dissection"]

# A pivot of D at or below this fraction of the largest pivot means the matrix is
# singular or indefinite to working precision: with ~1e-16 rounding per operation, a
# well-posed SPD system keeps its smallest pivot many orders above this.
_PIVOT_TOLERANCE = 1e-13


def _singular_values_hint(lower) -> str:
    """Where in the matrix a zero pivot comes from, when it can be seen from the values:
    an all-zero row, a zero diagonal entry, or two equal rows."""
    lower = sp.csc_matrix(lower)
    full = (lower + sp.tril(lower, -1, format="csc").T).tocsr()
    full.eliminate_zeros()
    counts = np.diff(full.indptr)
    if (counts == 0).any():
        row = int(np.flatnonzero(counts == 0)[0])
        return f"row and column {row} are all zero ({int((counts == 0).sum())} such row(s))"
    diagonal = full.diagonal()
    if (diagonal == 0).any():
        row = int(np.flatnonzero(diagonal == 0)[0])
        return f"the diagonal entry [{row}, {row}] is 0 ({int((diagonal == 0).sum())} such entries)"
    seen: dict[tuple, int] = {}
    for row in range(full.shape[0]):
        start, end = full.indptr[row], full.indptr[row + 1]
        key = (full.indices[start:end].tobytes(), full.data[start:end].tobytes())
        if key in seen:
            return f"rows {seen[key]} and {row} are equal"
        seen[key] = row
    return "its rows are linearly dependent"


def _factorise(build, lower, name: str):
    """Run a compiled factorisation, naming what in the values makes it singular.

    ``lower`` gives the lower triangle, on demand: only a failure needs it.
    """
    try:
        return build()
    except ValueError as exc:
        if "zero pivot" not in str(exc):
            raise
        raise ValueError(f"{name} is singular: its LDL^T factorisation met an exactly zero pivot; "
                         f"{_singular_values_hint(lower())}") from None


def _as_symmetric_csc_lower(matrix, name: str, symmetry_tolerance: float):
    """The lower triangle of a validated square, symmetric, finite sparse matrix as CSC."""
    if not sp.issparse(matrix):
        dense = as_array(matrix, name)
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


class SparseCholesky(Immutable):
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
        # NaN would make every comparison false and switch the symmetry check off.
        tolerance = as_positive(symmetry_tolerance, "symmetry_tolerance", allow_zero=True)
        lower = _as_symmetric_csc_lower(matrix, "matrix", tolerance)
        self._lower = lower  # kept for pickling: a refactorisation gives the same factor
        self._n = lower.shape[0]
        self._factor = _factorise(lambda: _core.SparseCholesky(
            self._n,
            np.ascontiguousarray(lower.indptr, dtype=np.int64),
            np.ascontiguousarray(lower.indices, dtype=np.int64),
            np.ascontiguousarray(lower.data, dtype=np.float64),
            _PIVOT_TOLERANCE,
        ), lambda: lower, "matrix")

    def __reduce__(self):
        return _refactorise, (self._lower,)

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
        return _solve(self._factor, self._n, rhs)


def _solve(factor, n: int, rhs) -> np.ndarray:
    """Validate ``rhs`` ((n,) or (n, k), finite) and solve with a compiled factor."""
    array = as_array(rhs, "rhs")
    vector = array.ndim == 1
    if vector:
        array = array[:, None]
    if array.ndim != 2 or array.shape[0] != n:
        raise ValueError(f"rhs must have shape ({n},) or ({n}, k), got {np.shape(rhs)}")
    check_finite(array, "rhs")
    if array.shape[1] == 0 or n == 0:
        solution = np.zeros(array.shape)
    else:
        # Fortran order lets the core read each column in place.
        solution = np.ascontiguousarray(factor.solve(np.asfortranarray(array)))
    return solution[:, 0] if vector else solution


class PatternCholesky:
    """Symmetric positive-definite matrices with one sparsity pattern, factorised in turn.

    An iterative fit often solves a linear system whose values change from one
    iteration to the next while its structure does not. The fill-reducing ordering
    and the symbolic analysis depend on the structure only, so they are computed
    once, here; each :meth:`factorise` computes only the numeric factor. The values
    arrive as a plain array in the order of the pattern's entries, with no
    sparse-matrix conversion or symmetry check: the caller owns the pattern and
    fills it.

    The default method is a supernodal Cholesky factorisation P A P^T = L L^T: the
    columns of L that share one row structure are grouped into dense blocks, and
    nearly all the arithmetic runs in dense matrix-product kernels (compiled for
    AVX2 + FMA too, and chosen at run time). Factorisations large enough to gain
    from threads (about 2,000 unknowns of a lattice system and up) run disjoint parts
    of the elimination tree on separate threads (as many as
    :func:`tpscore.num_threads` gives when the pattern is analysed); the results do
    not depend on the thread count.
    ``method="simplicial"`` is the column-by-column L D L^T factorisation (Eigen's
    SimplicialLDLT) the supernodal one is checked and timed against.

    Parameters
    ----------
    indptr, indices : array_like of int
        The pattern of the LOWER triangle (diagonal included) in compressed-sparse-
        column form: column j holds the rows ``indices[indptr[j]:indptr[j + 1]]``,
        strictly increasing and all >= j. The order is n = len(indptr) - 1.
    ordering : array_like of int, shape (n,), optional
        The elimination order: ``ordering[k]`` is the unknown eliminated k-th (a
        permutation of ``range(n)``), for a caller who knows the problem's geometry
        (see :func:`grid_nested_dissection`). Default: approximate minimum degree.
        The factorisation may reorder unknowns further where that cannot add fill
        (a postorder of the elimination tree). Supernodal method only.
    method : {"supernodal", "simplicial"}, default "supernodal"

    Raises
    ------
    ValueError
        If the arrays do not describe such a pattern, or ``ordering`` is not a
        permutation of ``range(n)``.

    Examples
    --------
    >>> pattern = PatternCholesky([0, 2, 4, 5], [0, 1, 1, 2, 2])
    >>> pattern.factorise([2.0, -1.0, 2.0, -1.0, 2.0])
    >>> pattern.solve([1.0, 0.0, 1.0])
    array([1., 1., 1.])
    >>> pattern.factorise([4.0, 0.0, 4.0, 0.0, 4.0])
    >>> pattern.solve([1.0, 0.0, 1.0])
    array([0.25, 0.  , 0.25])
    """

    def __init__(self, indptr, indices, *, ordering=None, method: str = "supernodal"):
        indptr = np.asarray(indptr)
        indices = np.asarray(indices)
        for name, array in (("indptr", indptr), ("indices", indices)):
            if array.ndim != 1 or not (np.issubdtype(array.dtype, np.integer) or array.size == 0):
                raise ValueError(f"{name} must be a 1-D integer array, got shape {array.shape} "
                                 f"and dtype {array.dtype}")
        if len(indptr) == 0 or indptr[0] != 0:
            raise ValueError("indptr must start with 0")
        n = len(indptr) - 1
        if np.any(np.diff(indptr) < 0) or indptr[-1] != len(indices):
            raise ValueError(f"indptr must be nondecreasing and end at len(indices) = {len(indices)}, "
                             f"ends at {indptr[-1]}")
        if len(indices) >= 2**31 - 1:
            raise ValueError(f"the pattern has {len(indices)} entries; the limit is 2^31 - 1")
        columns = np.repeat(np.arange(n), np.diff(indptr))
        if len(indices) and (indices.min() < 0 or indices.max() >= n):
            raise ValueError(f"indices must lie in [0, {n})")
        if np.any(indices < columns):
            raise ValueError("the pattern must be the lower triangle: a row index lies above its column")
        same_column = columns[1:] == columns[:-1]
        if np.any(same_column & (np.diff(indices) <= 0)):
            raise ValueError("row indices must be strictly increasing within each column")
        if method not in ("supernodal", "simplicial"):
            raise ValueError(f"method must be 'supernodal' or 'simplicial', got {method!r}")
        if ordering is not None:
            if method != "supernodal":
                raise ValueError("ordering is used by the supernodal method only")
            ordering = np.asarray(ordering)
            if ordering.shape != (n,) or not (np.issubdtype(ordering.dtype, np.integer) or n == 0):
                raise ValueError(f"ordering must be a 1-D integer array of length {n}, got shape "
                                 f"{ordering.shape} and dtype {ordering.dtype}")
            if n and not np.array_equal(np.sort(ordering), np.arange(n)):
                raise ValueError(f"ordering must be a permutation of range({n})")
        self._n = n
        self._entries = len(indices)
        self._method = method
        indptr = np.ascontiguousarray(indptr, dtype=np.int64)
        indices = np.ascontiguousarray(indices, dtype=np.int64)
        self._pattern = (indptr, indices)  # to say where a singular matrix's zero pivot comes from
        if method == "simplicial":
            self._factor = _core.SimplicialPatternCholesky(n, indptr, indices)
        elif ordering is None:
            self._factor = _core.PatternCholesky(n, indptr, indices)
        else:
            self._factor = _core.PatternCholesky(n, indptr, indices,
                                                 np.ascontiguousarray(ordering, dtype=np.int64))

    @property
    def n(self) -> int:
        """Order of the matrices."""
        return self._n

    @property
    def entries(self) -> int:
        """Stored entries of the pattern (the length :meth:`factorise` expects)."""
        return self._entries

    @property
    def method(self) -> str:
        """``"supernodal"`` or ``"simplicial"``."""
        return self._method

    @property
    def factor_nonzeros(self) -> int | None:
        """Entries of L stored below its diagonal, explicit zeros of merged supernodes
        included (supernodal method; None for the simplicial one)."""
        return int(self._factor.factor_nonzeros) if self._method == "supernodal" else None

    def factorise(self, values, *, workers: int = -1) -> None:
        """Factorise the matrix with this pattern and ``values`` (one per entry, CSC order).

        ``workers``: the threads that may share the elimination tree's independent
        subtrees (supernodal method; -1 for all, 1 for serial). The factor is the same,
        bit for bit, with any count.

        Raises
        ------
        ValueError
            If the values are not finite or of the wrong length, or the matrix is not
            positive definite (as for :class:`SparseCholesky`). No factor is kept then.
        """
        array = np.ascontiguousarray(as_array(values, "values"))
        if array.shape != (self._entries,):
            raise ValueError(f"values must have shape ({self._entries},), got {array.shape}")
        check_finite(array, "values")
        threads = as_workers(workers)
        factorize = (partial(self._factor.factorize, workers=threads) if self._method == "supernodal"
                     else self._factor.factorize)
        _factorise(lambda: factorize(array, _PIVOT_TOLERANCE),
                   lambda: sp.csc_matrix((array, self._pattern[1], self._pattern[0]),
                                         shape=(self._n, self._n)), "the matrix")

    @property
    def factorised(self) -> bool:
        """Whether a factor is held (the last :meth:`factorise` succeeded)."""
        return bool(self._factor.factorised)

    @property
    def pivot_range(self) -> tuple[float, float]:
        """(smallest, largest) pivot of D in the last factor (for L L^T, the squared
        diagonal of L)."""
        return float(self._factor.min_pivot), float(self._factor.max_pivot)

    def solve(self, rhs) -> np.ndarray:
        """Solve A x = b with the last factor; ``rhs`` of shape (n,) or (n, k).

        Raises
        ------
        ValueError
            If no factor is held, or ``rhs`` is malformed or not finite.
        """
        if not self._factor.factorised:
            raise ValueError("no factor: call factorise() first (or the last one failed)")
        return _solve(self._factor, self._n, rhs)

    def __repr__(self) -> str:
        return f"PatternCholesky(n={self._n}, entries={self._entries}, method={self._method!r})"


def grid_nested_dissection(shape, reach: int = 1) -> np.ndarray:
    """A nested-dissection elimination order of the nodes of a 2-D grid.

    For the unknowns of a grid whose nodes couple with the nodes at most ``reach``
    rows and columns away (a stencil of (2 reach + 1)^2 nodes), a band of ``reach``
    node lines across the grid separates it into two halves that do not couple.
    Ordering each half first (recursively, cutting the longer side each time) and the
    band last keeps the Cholesky factor's fill near its minimum for a grid (George's
    nested dissection): the dense blocks are the bands, about sqrt(nodes) wide.

    Parameters
    ----------
    shape : (int, int)
        Rows and columns of the grid; node (r, c) is ``r * shape[1] + c``.
    reach : int
        How many rows and columns away a node's coupling reaches (3 for products of
        cubic B-spline stencils).

    Returns
    -------
    ndarray of int64, shape (rows * columns,)
        The node eliminated k-th at position k.
    """
    rows, columns = (int(v) for v in shape)
    reach = int(reach)
    if rows < 0 or columns < 0 or reach < 1:
        raise ValueError(f"shape must be two non-negative sizes and reach >= 1, got {shape}, {reach}")
    index = np.arange(rows * columns, dtype=np.int64).reshape(rows, columns)
    # a block this small is eliminated as one dense front anyway: splitting it
    # further only makes smaller fronts
    leaf = 2 * reach - 1
    order = []

    def dissect(block):
        height, width = block.shape
        if height <= leaf and width <= leaf or height * width == 0:
            order.append(block.ravel())
            return
        if height >= width:
            cut = (height - reach) // 2
            dissect(block[:cut])
            dissect(block[cut + reach:])
            order.append(block[cut:cut + reach].ravel())
        else:
            cut = (width - reach) // 2
            dissect(block[:, :cut])
            dissect(block[:, cut + reach:])
            order.append(block[:, cut:cut + reach].ravel())

    dissect(index)
    return np.concatenate(order) if order else np.zeros(0, dtype=np.int64)


def _refactorise(lower):
    """A SparseCholesky of the lower triangle it was made from: what unpickling calls."""
    return SparseCholesky(lower + sp.tril(lower, -1).T)

"""Reference for the sparse direct solve: SciPy's SuperLU (``splu`` / ``spsolve``)."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


def sparse_solve(matrix, rhs) -> np.ndarray:
    """Solve A x = b with scipy.sparse.linalg.spsolve; rhs (n,) or (n, k)."""
    rhs = np.asarray(rhs, dtype=np.float64)
    solution = spla.spsolve(sp.csc_matrix(matrix, dtype=np.float64), rhs)
    return np.asarray(solution).reshape(rhs.shape)


class SparseLU:
    """Factorise once with scipy.sparse.linalg.splu, then solve; the peer of SparseCholesky."""

    def __init__(self, matrix):
        self._lu = spla.splu(sp.csc_matrix(matrix, dtype=np.float64))

    def solve(self, rhs) -> np.ndarray:
        return self._lu.solve(np.asarray(rhs, dtype=np.float64))

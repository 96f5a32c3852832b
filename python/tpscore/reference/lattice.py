"""NumPy and SciPy references for the lattice kernels: the field's evaluation
(tpscore.lattice.BSplineLattice.evaluate) and the normal equations.

The scipy route to the block Gram matrix sum_i (b_i b_i^T) (x) Q_i of samples on a
B-spline lattice: one sparse product B^T diag(Q_kl) B per component pair (k, l),
stacked in component blocks [x; y; z]. Same conventions as
tpscore.lattice.LatticeSystem.data_term.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["block_gram", "evaluate"]


def evaluate(lattice, xy, node_values) -> np.ndarray:
    """The field of a :class:`tpscore.lattice.BSplineLattice` at points (m, 2) from its
    (n_nodes, k) node values, by gathering each point's 16 stencil nodes."""
    cols, weights = lattice._stencil(xy)
    node_values = np.asarray(node_values, dtype=np.float64).reshape(lattice.n_nodes, -1)
    return np.stack([(weights * node_values[:, k][cols]).sum(axis=1) for k in range(node_values.shape[1])],
                    axis=1)


def block_gram(basis, blocks) -> sp.csr_matrix:
    """(3 n, 3 n) block Gram matrix of a (m, n) sample basis and (m, 3, 3) weights Q_i."""
    basis = sp.csr_matrix(basis, dtype=np.float64)
    blocks = np.asarray(blocks, dtype=np.float64)
    return sp.bmat([[basis.T @ basis.multiply(blocks[:, k, l][:, None]) for l in range(3)]
                    for k in range(3)]).tocsr()

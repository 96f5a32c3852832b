"""Fits of a smooth 3-vector field on a uniform cubic B-spline lattice over the x-y
plane: the lattice (:class:`BSplineLattice`: stencils, evaluation, bending energy) and
the normal equations of a least-squares fit on it (:class:`LatticeSystem`), whose data
term a compiled kernel fills straight into one fixed sparsity pattern.

The dense registration of expression transfer (:func:`tpscore.register_surfaces`)
solves such a fit at every iteration; its reference is
:mod:`tpscore.reference.lattice`.
"""
from __future__ import annotations

import threading

import numpy as np
import scipy.sparse as sp

from . import _core
from .sparse import PatternCholesky, grid_nested_dissection

__all__ = ["BSplineLattice", "LatticeSystem", "symmetric_blocks", "SYMMETRIC_ENTRIES"]


def _cubic_bspline_weights(t: np.ndarray) -> np.ndarray:
    """(n, 4) uniform cubic B-spline weights of the nodes i-1, i, i+1, i+2 at t in [0, 1)."""
    s = 1.0 - t
    return np.stack([s ** 3, 3 * t ** 3 - 6 * t ** 2 + 4, -3 * t ** 3 + 3 * t ** 2 + 3 * t + 1,
                     t ** 3], axis=1) / 6.0


def _cubic_bspline_derivatives(t: np.ndarray) -> np.ndarray:
    """(n, 4) derivatives d/dt of :func:`_cubic_bspline_weights`."""
    s = 1.0 - t
    return np.stack([-0.5 * s ** 2, 1.5 * t ** 2 - 2.0 * t, -1.5 * t ** 2 + t + 0.5, 0.5 * t ** 2],
                    axis=1)


class BSplineLattice:
    """A uniform cubic B-spline lattice over an x-y rectangle.

    Parameters
    ----------
    lower, upper : (2,) array_like
        Corners of the x-y rectangle the field must cover (mm).
    spacing : float
        Node spacing (mm).
    """

    def __init__(self, lower, upper, spacing: float):
        lower = np.asarray(lower, dtype=np.float64)
        upper = np.asarray(upper, dtype=np.float64)
        self.spacing = float(spacing)
        # one node beyond each side: a cubic B-spline needs the nodes i-1 .. i+2
        self.origin = lower - self.spacing
        cells = np.ceil((upper - lower) / self.spacing).astype(int) + 1
        self.shape = (int(cells[1]) + 3, int(cells[0]) + 3)   # (rows along y, columns along x)

    @property
    def n_nodes(self) -> int:
        return self.shape[0] * self.shape[1]

    def _stencil(self, xy, derivative: str = ""):
        """For points (m, 2): the (m, 16) node indices each depends on, and their weights."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        g = (xy - self.origin) / self.spacing
        cell = np.floor(g).astype(np.int64)
        cell[:, 0] = np.clip(cell[:, 0], 1, self.shape[1] - 3)
        cell[:, 1] = np.clip(cell[:, 1], 1, self.shape[0] - 3)
        t = np.clip(g - cell, 0.0, 1.0)
        wx = _cubic_bspline_weights(t[:, 0])
        wy = _cubic_bspline_weights(t[:, 1])
        if derivative == "x":
            wx = _cubic_bspline_derivatives(t[:, 0]) / self.spacing
        elif derivative == "y":
            wy = _cubic_bspline_derivatives(t[:, 1]) / self.spacing
        elif derivative:
            raise ValueError(f"derivative must be '', 'x' or 'y', got {derivative!r}")
        offsets = np.arange(-1, 3)
        cols = (cell[:, 1, None, None] + offsets[None, :, None]) * self.shape[1] \
            + (cell[:, 0, None, None] + offsets[None, None, :])
        return cols.reshape(-1, 16), (wy[:, :, None] * wx[:, None, :]).reshape(-1, 16)

    def basis(self, xy, derivative: str = "") -> sp.csr_matrix:
        """(m, n_nodes) sparse matrix: the field at points (m, 2) is basis @ node_values;
        with ``derivative="x"`` (``"y"``) its derivative along x (y), per mm."""
        return self._stencil_matrix(*self._stencil(xy, derivative))

    def _stencil_matrix(self, cols, values) -> sp.csr_matrix:
        """The (m, n_nodes) sparse matrix of :meth:`_stencil`'s node indices and weights."""
        rows = np.repeat(np.arange(len(cols)), 16)
        return sp.csr_matrix((values.ravel(), (rows, cols.ravel())), shape=(len(cols), self.n_nodes))

    def evaluate(self, xy, node_values) -> np.ndarray:
        """The field at points (m, 2) from its (n_nodes, k) node values: ``basis(xy) @
        node_values`` without building the matrix (compiled, threaded; NaN rows for
        non-finite points). Its reference is :func:`tpscore.reference.lattice.evaluate`."""
        xy = np.ascontiguousarray(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
        node_values = np.ascontiguousarray(np.asarray(node_values, dtype=np.float64).reshape(self.n_nodes, -1))
        return _core.lattice_evaluate(xy, float(self.origin[0]), float(self.origin[1]), self.spacing,
                                      self.shape[0], self.shape[1], node_values)

    def bending(self) -> sp.csr_matrix:
        """(n_nodes, n_nodes) thin-plate bending energy of the node values (second
        differences: xx, 2 xy, yy), scaled to mm^-2 so that it does not depend on the
        spacing."""
        rows, cols = self.shape
        index = np.arange(self.n_nodes).reshape(rows, cols)

        def operator(stencil):
            """Rows applying a 3 x 3 stencil at every interior node."""
            r, c = np.meshgrid(np.arange(1, rows - 1), np.arange(1, cols - 1), indexing="ij")
            centre = r.ravel(), c.ravel()
            entries_r, entries_c, entries_v = [], [], []
            for (dr, dc), v in stencil.items():
                entries_r.append(np.arange(len(centre[0])))
                entries_c.append(index[centre[0] + dr, centre[1] + dc])
                entries_v.append(np.full(len(centre[0]), v))
            return sp.csr_matrix((np.concatenate(entries_v),
                                  (np.concatenate(entries_r), np.concatenate(entries_c))),
                                 shape=(len(centre[0]), self.n_nodes))

        dxx = operator({(0, -1): 1.0, (0, 0): -2.0, (0, 1): 1.0})
        dyy = operator({(-1, 0): 1.0, (0, 0): -2.0, (1, 0): 1.0})
        dxy = operator({(-1, -1): 0.25, (-1, 1): -0.25, (1, -1): -0.25, (1, 1): 0.25})
        energy = dxx.T @ dxx + 2.0 * dxy.T @ dxy + dyy.T @ dyy
        return (energy / self.spacing ** 2).tocsr()


# The unique entries of a symmetric 3 x 3 block in the compiled kernel's order (xx, xy,
# xz, yy, yz, zz), and the slot of entry (k, l) among them.
SYMMETRIC_ENTRIES = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_SYMMETRIC_SLOT = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
# The forward node offsets (rows, columns) two cubic stencils can share, in the
# kernel's slot order: every unordered node pair once, under its lower-indexed node.
_NEIGHBOUR_OFFSETS = [(0, c) for c in range(4)] + [(r, c) for r in range(1, 4) for c in range(-3, 4)]


def symmetric_blocks(matrices) -> np.ndarray:
    """(m, 6) unique entries (xx, xy, xz, yy, yz, zz) of (m, 3, 3) symmetric matrices."""
    matrices = np.asarray(matrices, dtype=np.float64)
    return np.stack([matrices[:, k, l] for k, l in SYMMETRIC_ENTRIES], axis=1)


class LatticeSystem:
    """The normal equations of a least-squares fit of a 3-vector field on a
    :class:`BSplineLattice`, for fixed sample points, in the node values with
    component blocks [x; y; z] (3 n_nodes unknowns).

    Every matrix such a fit forms (the bending energy, landmark terms, each
    iteration's data term) couples only nodes that two cubic stencils can share, at
    most 3 rows and 3 columns apart, so one sparsity pattern holds them all. The
    pattern, the samples' stencils and the sparse factor's ordering and symbolic
    analysis are made here, once; an iteration then fills in values, with the data
    term's block Gram matrix from a compiled kernel, and refactorises.

    Parameters
    ----------
    lattice : BSplineLattice
    xy : (m, 2) array_like
        The sample points (mm).
    """

    def __init__(self, lattice: BSplineLattice, xy):
        self.lattice = lattice
        nodes, weights = lattice._stencil(xy)
        self._first_node = np.ascontiguousarray(nodes[:, 0])
        self._weights = np.ascontiguousarray(weights)
        self.basis = lattice._stencil_matrix(nodes, weights)
        self._build_pattern()
        # nested dissection of the node grid, the three components of a node kept
        # together (they share one row structure, so they form one 3-wide block)
        node_order = grid_nested_dissection(lattice.shape, reach=3)
        self._ordering = (node_order[:, None] + lattice.n_nodes * np.arange(3)).ravel()
        # factors not in use: a solve takes one (a new one when two threads solve at
        # once, as the two sides of a cut do), so that it holds its own numeric factor
        self._factor = self._new_factor()
        self._idle_factors = [self._factor]
        self._solving = 0  # solves in flight
        self._factors_lock = threading.Lock()

    def _new_factor(self) -> PatternCholesky:
        return PatternCholesky(self.indptr, self.indices, ordering=self._ordering)

    def _build_pattern(self) -> None:
        n = self.lattice.n_nodes
        lattice_rows, lattice_columns = self.lattice.shape
        node = np.arange(n)
        node_row, node_column = np.divmod(node, lattice_columns)
        entry_rows, entry_columns, sources = [], [], []
        for slot, (dr, dc) in enumerate(_NEIGHBOUR_OFFSETS):
            inside = (node_row + dr < lattice_rows) & (node_column + dc >= 0) & (node_column + dc < lattice_columns)
            p = node[inside]
            q = p + dr * lattice_columns + dc
            for k in range(3):
                for m in range(3):
                    source = (p * len(_NEIGHBOUR_OFFSETS) + slot) * len(SYMMETRIC_ENTRIES) + _SYMMETRIC_SLOT[k, m]
                    # the block couples p with q and q with p alike (it is symmetric)
                    entry_rows += [k * n + q, k * n + p]
                    entry_columns += [m * n + p, m * n + q]
                    sources += [source, source]
        entry_rows = np.concatenate(entry_rows)
        entry_columns = np.concatenate(entry_columns)
        sources = np.concatenate(sources)
        lower = entry_rows >= entry_columns
        keys, first = np.unique(entry_columns[lower] * (3 * n) + entry_rows[lower], return_index=True)
        self._keys = keys
        self._take = sources[lower][first]
        self.indices = keys % (3 * n)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(keys // (3 * n), minlength=3 * n))])

    @property
    def n(self) -> int:
        """Unknowns: three per node."""
        return 3 * self.lattice.n_nodes

    def aligned(self, matrix) -> np.ndarray:
        """The values of a symmetric (n, n) sparse matrix in the pattern's entry order
        (its lower triangle; duplicates summed).

        Raises
        ------
        ValueError
            If the matrix has an entry outside the pattern.
        """
        lower = sp.tril(sp.coo_matrix(matrix))
        keys = lower.col.astype(np.int64) * self.n + lower.row
        where = np.minimum(np.searchsorted(self._keys, keys), len(self._keys) - 1)
        outside = self._keys[where] != keys
        if np.any(outside & (lower.data != 0)):
            raise ValueError("the matrix couples nodes farther apart than two stencils reach")
        return np.bincount(where[~outside], weights=lower.data[~outside], minlength=len(self._keys))

    def data_term(self, blocks) -> np.ndarray:
        """The values, in the pattern's entry order, of sum_i (b_i b_i^T) (x) Q_i over
        the samples (b_i: a sample's 16 B-spline weights; Q_i: a symmetric 3 x 3
        weight given as its (m, 6) :data:`SYMMETRIC_ENTRIES`)."""
        blocks = np.ascontiguousarray(blocks, dtype=np.float64)
        if blocks.shape != (len(self._first_node), len(SYMMETRIC_ENTRIES)):
            raise ValueError(f"blocks must have shape ({len(self._first_node)}, 6), got {blocks.shape}")
        gram = _core.lattice_block_gram(self._first_node, self._weights, blocks,
                                        self.lattice.shape[0], self.lattice.shape[1])
        return gram.ravel()[self._take]

    def matrix(self, values) -> sp.csc_matrix:
        """The symmetric (n, n) matrix with ``values`` in the pattern (for inspection)."""
        lower = sp.csc_matrix((values, self.indices, self.indptr), shape=(self.n, self.n))
        return (lower + sp.tril(lower, -1).T).tocsc()

    def solve(self, values, rhs) -> np.ndarray:
        """Factorise the matrix with ``values`` and solve it for ``rhs`` (n,) or (n, k).

        Threads may solve at once. A factorisation alone shares the elimination tree's
        subtrees among the kernel threads; one that starts while another thread solves
        this system stays on its own thread, since the cores are taken (the two sides
        of a cut, registered side by side). The result is the same either way, bit for
        bit."""
        with self._factors_lock:
            factor = self._idle_factors.pop() if self._idle_factors else None
            self._solving += 1
            alone = self._solving == 1
        if factor is None:
            factor = self._new_factor()
        try:
            factor.factorise(values, workers=-1 if alone else 1)
            return factor.solve(rhs)
        finally:
            with self._factors_lock:
                self._idle_factors.append(factor)
                self._solving -= 1

"""Dense radial basis function interpolation and the 3D thin-plate spline.

A fitted interpolant is

    f(x) = [1 x y z] A + sum_i W_i phi(|x - p_i|),   with P^T W = 0,

over centres p_i (mm), with P = [1 x y z] of the centres. Fitting solves

    [ K + sign * smoothing * I   P ] [W]   [values]
    [ P^T                        0 ] [A] = [  0   ]

with K_ij = phi(|p_i - p_j|), in coordinates centred and scaled for conditioning (the
exposed weights and affine part are in the original coordinates). Every kernel here
is conditionally positive definite (with the sign below), so the compiled core solves
by the null-space method: projected onto W with P^T W = 0 the system is symmetric
positive definite, and a blocked, threaded Cholesky factorisation (half the work of
an LU) solves it. Results do not depend on the thread count.

Kernels (r in mm; the names are explicit because they are easily confused):

=============  =========================  ====================================  ====
name           phi(r)                     SciPy RBFInterpolator equivalent      sign
=============  =========================  ====================================  ====
tps            r^2 ln r^2, phi(0) = 0     ``thin_plate_spline`` (r^2 ln r)      +1
biharmonic     r                          ``linear`` (-r)                       -1
triharmonic    r^3                        ``cubic`` (r^3)                       +1
multiquadric   +sqrt(1 + (eps r)^2)       ``multiquadric`` (-sqrt(1+(eps r)^2)) -1
gaussian       exp(-(eps r)^2)            ``gaussian``                          +1
=============  =========================  ====================================  ====

Each interpolant equals SciPy's with ``degree=1`` (same function, weights scaled by
the constant factor between the kernels). `sign` makes ``sign * K`` conditionally
positive definite; smoothing is applied with it, so a larger ``smoothing >= 0``
always gives a smoother fit that interpolates less exactly (for biharmonic this is
the ``K - rho I`` of template adaptation). SciPy adds its ``smoothing`` to the
diagonal of its own kernel matrix, so ``RBF(..., smoothing=s)`` equals
``RBFInterpolator(..., smoothing=s)`` for every kernel here except tps, whose SciPy
kernel is half of ours: ``smoothing=s`` here is SciPy's ``smoothing=s / 2``.
"""
from __future__ import annotations

import math

import numpy as np

from . import _core
from ._validation import Immutable, MAX_DENSE_ELEMENTS, as_points, as_positive, as_values, check_result_size

__all__ = ["RBF", "TPS", "RBF_KERNELS"]

#: Kernel names accepted by :class:`RBF`, mapped to the core's enumeration.
RBF_KERNELS: dict[str, _core.RbfKernel] = {
    "tps": _core.RbfKernel.tps,
    "biharmonic": _core.RbfKernel.biharmonic,
    "triharmonic": _core.RbfKernel.triharmonic,
    "multiquadric": _core.RbfKernel.multiquadric,
    "gaussian": _core.RbfKernel.gaussian,
}
_KERNELS_WITH_EPSILON = ("multiquadric", "gaussian")

# Centres closer than this fraction of the centres' extent (largest side of their
# bounding box) coincide: the two kernel rows are then equal to about 1e-16 and the
# interpolation system is singular to working precision.
DUPLICATE_RELATIVE_TOLERANCE = 1e-8
# Centres whose spread across some direction is below this fraction of their extent
# are treated as flat (coplanar or collinear): the affine part [1 x y z] then has
# no unique solution.
FLATNESS_RELATIVE_TOLERANCE = 1e-8
# [1 x y z] has 4 unknowns per value column, and a thin-plate spline needs at least
# one radial degree of freedom beyond them.
MIN_CENTRES = 5
#: The most centres of a dense fit: its n x n kernel matrix stays within the dense-array
#: budget (16,384 centres: 2 GiB). Beyond it the fit would also take minutes; the
#: compactly supported :class:`tpscore.CSRBF` solves a sparse system instead.
MAX_DENSE_CENTRES = math.isqrt(MAX_DENSE_ELEMENTS)


def _gib(n_bytes: float) -> str:
    return f"{n_bytes / 2**30:.1f} GiB"


def _check_dense_size(n: int) -> None:
    """Refuse, before anything is allocated, a dense fit whose matrix is too large."""
    if n > MAX_DENSE_CENTRES:
        raise ValueError(
            f"centres: a dense RBF fit of {n} centres needs an {n} x {n} matrix "
            f"({_gib(8.0 * n * n)}, and up to three times that when the system is not "
            f"definite); tpscore fits at most {MAX_DENSE_CENTRES} centres densely. Use "
            "tpscore.CSRBF (compact support, a sparse system) for large point sets")


def _check_not_empty(centres: np.ndarray, name: str) -> None:
    if len(centres) == 0:
        raise ValueError(f"{name} is empty: an RBF fit needs at least {MIN_CENTRES} centres")


def _check_evaluated(result: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Refuse a result that overflowed: rather an error than NaN handed back."""
    if not np.isfinite(result).all():
        _check_overflow(int(np.flatnonzero(~np.isfinite(result).all(axis=1))[0]), queries)
    return result


def _check_overflow(row: int, queries: np.ndarray) -> None:
    """Refuse an evaluation whose row ``row`` overflowed (-1: none did)."""
    if row >= 0:
        raise ValueError(
            f"points row {row} ({queries[row].tolist()}): the interpolant's value "
            "overflows float64 there; the point is too far from the centres")


def _read_only(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)
    return array


# A fixed generic direction for sorting centres (off the axes and the diagonals, so that
# no axis-aligned plane of centres projects onto one value).
_PROJECTION_DIRECTION = np.array([0.5773502691896258, 0.5783502691896258, 0.5803502691896258])
_PROJECTION_NORM = float(np.linalg.norm(_PROJECTION_DIRECTION))


def _find_coincident_pair(centres: np.ndarray, tolerance: float) -> tuple[int, int, float] | None:
    """The first pair of centres closer than `tolerance` (mm), or None.

    Sorts the centres along a fixed generic direction and compares each with its
    successors while their projections lie within `tolerance`: O(n log n) for any
    cloud that is not itself crowded along that direction.
    """
    projection = centres @ _PROJECTION_DIRECTION
    # |d . u| <= |d| |u|, so points within `tolerance` project within tolerance * |u|.
    window = tolerance * _PROJECTION_NORM
    # The usual answer, no pair, needs only the sorted projections (a fit of 100
    # centres spent a tenth of its time here before this shortcut).
    if not (np.diff(np.sort(projection)) <= window).any():
        return None
    order = np.argsort(projection, kind="stable")
    sorted_projection = projection[order]
    sorted_centres = centres[order]
    n = len(centres)
    offset = 1
    while offset < n:
        close = sorted_projection[offset:] - sorted_projection[:-offset] <= window
        if not close.any():
            return None
        candidates = np.flatnonzero(close)
        distances = np.linalg.norm(
            sorted_centres[candidates + offset] - sorted_centres[candidates], axis=1)
        hits = candidates[distances <= tolerance]
        if hits.size:
            pairs = np.sort(np.stack([order[hits], order[hits + offset]], axis=1), axis=1)
            first = np.lexsort((pairs[:, 1], pairs[:, 0]))[0]
            i, j = (int(v) for v in pairs[first])
            return i, j, float(np.linalg.norm(centres[i] - centres[j]))
        offset += 1
    return None


def _affine_rank(centres: np.ndarray, extent: float) -> int:
    """Rank of [1 x y z] over the centres, flatness judged relative to `extent`."""
    centred = centres - centres.sum(axis=0) / len(centres)
    # Fast path for the usual, clearly three-dimensional cloud: with G = X^T X of the
    # centred points and eigenvalues l1 >= l2 >= l3, l1 l2 <= trace^2 / 4 and
    # l1 <= trace, so det(G) > 1e-6 trace^3 gives l3 / l1 > 4e-6. And l1 >= extent^2 / 2
    # (the two extreme points along the widest side), so the smallest singular value
    # of X is then above 1e-3 extent, far above the flatness tolerance. The determinant
    # of a 3 x 3 matrix that well conditioned is accurate to rounding, so the test
    # cannot pass for a flat cloud. Anything else goes to the SVD (3x slower at n = 100).
    (a, b, c), (_, d, e), (_, _, f) = (centred.T @ centred).tolist()
    trace = a + d + f
    determinant = a * (d * f - e * e) - b * (b * f - c * e) + c * (b * e - c * d)
    if determinant > 1e-6 * trace**3:
        return 4
    singular_values = np.linalg.svd(centred / extent, compute_uv=False)
    return 1 + int(np.count_nonzero(singular_values > FLATNESS_RELATIVE_TOLERANCE))


def _check_geometry(centres: np.ndarray, allow_coincident: bool) -> None:
    n = len(centres)
    if n < MIN_CENTRES:
        raise ValueError(
            f"centres: at least {MIN_CENTRES} are needed (4 for the affine part "
            f"[1 x y z] and at least one more for the radial part), got {n}")
    extent = float((centres.max(axis=0) - centres.min(axis=0)).max())
    if extent == 0.0:
        raise ValueError(f"centres: all {n} centres coincide")
    if not allow_coincident:
        pair = _find_coincident_pair(centres, DUPLICATE_RELATIVE_TOLERANCE * extent)
        if pair is not None:
            i, j, distance = pair
            raise ValueError(
                f"centres {i} and {j} coincide (distance {distance:.3g} mm, below "
                f"{DUPLICATE_RELATIVE_TOLERANCE:g} of the centres' extent {extent:.3g} mm); "
                "remove one, or pass smoothing > 0 to fit through both approximately")
    rank = _affine_rank(centres, extent)
    if rank < 4:
        shape = {3: "coplanar", 2: "collinear", 1: "coincident"}[rank]
        raise ValueError(
            f"the affine part is undetermined: centres are {shape} (rank {rank} of "
            "[1 x y z]); a 3D RBF needs centres that span a volume")


class RBF(Immutable):
    """A dense radial basis function interpolant with an affine part, in 3D.

    ``f(x) = [1 x y z] @ affine + sum_i weights[i] * phi(|x - centres[i]|)``, fitted so
    that ``f(centres) == values`` (approximately, with smoothing > 0). See the module
    docstring for the kernels, their SciPy equivalents and the smoothing convention.

    Parameters
    ----------
    centres : array_like, shape (n, 3)
        Centre positions in mm, n >= 5, distinct, not all on one plane.
    values : array_like, shape (n,) or (n, k)
        Values at the centres (any units; k columns are fitted independently).
        A 1-D array is treated as k = 1.
    kernel : {"tps", "biharmonic", "triharmonic", "multiquadric", "gaussian"}
        The radial function phi; "tps" is r^2 ln r^2.
    smoothing : float, optional
        lambda >= 0, added to the kernel matrix diagonal with the kernel's
        definiteness sign: ``K + sign * lambda * I``. Units of phi (mm^2 for tps,
        mm for biharmonic, mm^3 for triharmonic, none for gaussian and
        multiquadric). 0 interpolates exactly; large values approach the affine
        least-squares fit. With smoothing > 0, coincident centres are allowed.
    epsilon : float, optional
        Shape parameter in 1/mm, required (> 0) for "gaussian" and "multiquadric"
        and not accepted for the scale-free kernels.

    Raises
    ------
    ValueError
        Unknown kernel, bad epsilon or smoothing, wrong shapes, complex, NaN or
        infinite input, coordinates beyond +-1e15 mm, fewer than 5 or more than
        :data:`MAX_DENSE_CENTRES` centres (use :class:`tpscore.CSRBF`), coincident
        centres (naming their indices), coplanar or collinear centres, or a
        numerically singular system; and, when evaluated, a point so far from the
        centres that the value overflows.
    MemoryError
        The machine cannot give the n x n matrix; the message says how much it needs.

    Notes
    -----
    A fitted object is immutable (its arrays are read-only) and its methods release
    the GIL, so several threads may evaluate it at once.
    """

    __slots__ = ("_model", "_kernel", "_n_values", "_arrays", "_inputs")

    def __init__(self, centres, values, kernel: str = "tps", *, smoothing: float = 0.0,
                 epsilon: float | None = None):
        if not isinstance(kernel, str) or kernel not in RBF_KERNELS:
            raise ValueError(
                f"kernel must be one of {', '.join(repr(k) for k in RBF_KERNELS)}, "
                f"got {kernel!r}")
        if kernel in _KERNELS_WITH_EPSILON:
            if epsilon is None:
                raise ValueError(f"epsilon (1/mm) is required for kernel {kernel!r}")
            epsilon_value = as_positive(epsilon, "epsilon")
        else:
            if epsilon is not None:
                raise ValueError(
                    f"epsilon applies only to kernels {_KERNELS_WITH_EPSILON}; kernel "
                    f"{kernel!r} is scale-free, so pass epsilon=None")
            epsilon_value = 0.0
        smoothing_value = as_positive(smoothing, "smoothing", allow_zero=True)
        centres_array = as_points(centres, "centres")
        _check_not_empty(centres_array, "centres")  # before the values are matched to them
        values_array = as_values(values, len(centres_array), "values")
        if values_array.shape[1] == 0:
            raise ValueError("values must have at least one column, got shape "
                             f"{values_array.shape}")
        self._fit(centres_array, values_array, kernel, smoothing_value, epsilon_value)

    def __reduce__(self):
        # the fit is deterministic: refitting the same inputs with the same build gives
        # the same model, to the bit (a pickle ships the inputs, not the compiled object)
        return _refit, (type(self), *self._inputs)

    def _fit(self, centres: np.ndarray, values: np.ndarray, kernel: str, smoothing: float,
             epsilon: float) -> None:
        """Fit validated, C-contiguous float64 centres (n, 3) and values (n, k)."""
        _check_dense_size(len(centres))
        _check_geometry(centres, allow_coincident=smoothing > 0)
        try:
            model = _core.rbf_fit(centres, values, RBF_KERNELS[kernel], epsilon, smoothing)
        except ValueError as exc:
            raise ValueError(f"cannot fit the {kernel} RBF: {exc}") from None
        except MemoryError:
            n = len(centres)
            raise MemoryError(
                f"a dense RBF fit of {n} centres needs about {_gib(8.0 * n * n)} of memory "
                f"(up to {_gib(24.0 * n * n)}), more than the system could give; use "
                "tpscore.CSRBF for large point sets") from None
        setter = object.__setattr__
        setter(self, "_model", model)
        setter(self, "_kernel", kernel)
        setter(self, "_n_values", values.shape[1])
        # centres, weights and affine are copied out of the model on first use: a fit
        # that is only evaluated (the usual TPS warp) never needs them, and the three
        # copies were a sixth of a 100-centre fit.
        setter(self, "_arrays", {})
        setter(self, "_inputs", (_read_only(centres.copy()), _read_only(values.copy()), kernel, smoothing, epsilon))

    def _array(self, name: str) -> np.ndarray:
        array = self._arrays.get(name)
        if array is None:
            array = self._arrays.setdefault(name, _read_only(getattr(self._model, name)))
        return array

    def __setattr__(self, name, value):
        raise AttributeError(f"{type(self).__name__} is immutable once fitted")

    # --- evaluation -------------------------------------------------------------
    def __call__(self, points) -> np.ndarray:
        """Evaluate f at query points.

        Parameters
        ----------
        points : array_like, shape (m, 3)
            Query positions in mm.

        Returns
        -------
        numpy.ndarray, shape (m, k)
            f at each point (k columns even when the values were 1-D).

        Raises
        ------
        ValueError
            Bad points, a point where f overflows, or m * k above the dense-array
            budget (``_validation.MAX_DENSE_ELEMENTS``, 2 GiB of result), refused
            before the points are converted; evaluate in chunks of rows instead.
        """
        check_result_size(points, self._n_values)  # before the points are converted
        queries = as_points(points, "points")
        result = np.empty((len(queries), self._n_values))
        # the kernel checks each row for overflow as it writes it
        _check_overflow(self._model.evaluate_into(queries, result), queries)
        return result

    def displacement(self, points) -> np.ndarray:
        """Evaluate the displacement f(x) - x at query points (3 values only).

        Computed without subtracting two large coordinates, so it stays accurate far
        from the origin.

        Parameters
        ----------
        points : array_like, shape (m, 3)
            Query positions x in mm.

        Returns
        -------
        numpy.ndarray, shape (m, 3)
            f(x) - x in mm.

        Raises
        ------
        ValueError
            As :meth:`__call__` (a result of at most 2 GiB: 89,478,485 points).
        """
        if self._n_values != 3:
            raise ValueError(
                f"displacement needs values with 3 columns (a map of 3D points), "
                f"this RBF has {self._n_values}")
        check_result_size(points, 3)
        queries = as_points(points, "points")
        result = np.empty((len(queries), 3))
        _check_overflow(self._model.displacement_into(queries, result), queries)
        return result

    def evaluation_matrix(self, points) -> np.ndarray:
        """The matrix E with ``E @ coefficients == f(points)``.

        ``E = [phi(|x - p_j|) for each centre j | 1 x y z]``, in the original
        coordinates. Because f is linear in the values, E lets a caller apply many
        value sets (animation frames, say) to the same points with one product.

        Parameters
        ----------
        points : array_like, shape (m, 3)
            Query positions in mm.

        Returns
        -------
        numpy.ndarray, shape (m, n + 4)

        Raises
        ------
        ValueError
            If m * (n + 4) exceeds the dense-array budget
            (``_validation.MAX_DENSE_ELEMENTS``); evaluate in chunks of rows instead.
        """
        # The size is checked before any conversion, which could itself copy a
        # large (for example broadcast) input.
        shape = np.shape(points)
        columns = self._model.size + 4
        if len(shape) == 2 and shape[0] * columns > MAX_DENSE_ELEMENTS:
            raise ValueError(
                f"points: the evaluation matrix would be {shape[0]} x {columns} "
                f"= {shape[0] * columns:.3g} float64 values, more than the "
                f"limit of {MAX_DENSE_ELEMENTS:.3g}; pass the points in chunks of at "
                f"most {max(1, MAX_DENSE_ELEMENTS // columns)} rows")
        queries = as_points(points, "points")
        return _check_evaluated(self._model.evaluation_matrix(queries), queries)

    # --- the fitted model -----------------------------------------------------------
    @property
    def kernel(self) -> str:
        """Name of the radial function phi."""
        return self._kernel

    @property
    def smoothing(self) -> float:
        """lambda >= 0 as passed (units of phi)."""
        return self._model.smoothing

    @property
    def epsilon(self) -> float | None:
        """Shape parameter in 1/mm (gaussian, multiquadric), else None."""
        return self._model.epsilon if self._kernel in _KERNELS_WITH_EPSILON else None

    @property
    def centres(self) -> np.ndarray:
        """(n, 3) centres in mm (read-only)."""
        return self._array("centres")

    @property
    def weights(self) -> np.ndarray:
        """(n, k) radial weights W in original coordinates (read-only)."""
        return self._array("weights")

    @property
    def affine(self) -> np.ndarray:
        """(4, k) affine part A (rows: constant, x, y, z) in original coordinates (read-only)."""
        return self._array("affine")

    @property
    def coefficients(self) -> np.ndarray:
        """(n + 4, k) ``[weights; affine]``, matching :meth:`evaluation_matrix` (read-only)."""
        # Stacked on request rather than at every fit: few callers need it.
        return _read_only(np.concatenate([self.weights, self.affine], axis=0))

    @property
    def bending_energy(self) -> float:
        """``trace(W^T K W)``, K the centres' kernel matrix without smoothing.

        In original coordinates, units values^2 / phi. For tps and triharmonic it is
        >= 0 and proportional to the bending energy the spline minimises; for
        biharmonic and multiquadric it is <= 0 (their kernels are conditionally
        negative definite). It is not invariant to a change of length units.
        """
        return self._model.bending_energy

    @property
    def condition_number(self) -> float:
        """Estimated 1-norm condition number of the solved (normalised) system.

        ``||S||_1`` times an estimate of ``||S^-1||_1`` (Hager and Higham's estimator,
        as in LAPACK's ``dlacn2``: a lower bound, in practice within a factor of 3) for
        the saddle-point matrix S in the centred and scaled coordinates the fit uses,
        with the [1 x y z] rows and columns scaled to the kernel block (not of the
        system in the original coordinates, which is usually far worse conditioned).
        A fit whose estimate exceeds 1 / machine epsilon is refused as numerically
        singular.
        """
        return 1.0 / self._model.rcond

    def __repr__(self) -> str:
        extra = f", epsilon={self._model.epsilon:g}" if self.epsilon is not None else ""
        return (f"{type(self).__name__}(kernel={self._kernel!r}, centres={self._model.size}, "
                f"values={self._n_values}, smoothing={self.smoothing:g}{extra}, "
                f"condition_number={self.condition_number:.3g})")


def _refit(cls, centres, values, kernel, smoothing, epsilon):
    """A fitted RBF (or TPS) from its validated inputs: what unpickling calls."""
    fitted = object.__new__(cls)
    fitted._fit(np.ascontiguousarray(centres), np.ascontiguousarray(values), kernel, smoothing, epsilon)
    return fitted


class TPS(RBF):
    """The 3D thin-plate spline that maps source points onto target points.

    ``TPS(source, target)(source) == target`` (to rounding; approximately with
    smoothing > 0). This is :class:`RBF` with kernel ``"tps"`` (U(r) = r^2 ln r^2) and
    values = target; ``displacement(x)`` is the warp's f(x) - x.

    Parameters
    ----------
    source : array_like, shape (n, 3)
        Source landmarks in mm (n >= 5, distinct, not coplanar).
    target : array_like, shape (n, 3)
        Where each source landmark goes, in mm.
    smoothing : float, optional
        lambda >= 0 in mm^2 (see :class:`RBF`); 0 interpolates exactly.
    """

    __slots__ = ()

    def __init__(self, source, target, smoothing: float = 0.0):
        source_array = as_points(source, "source")
        _check_not_empty(source_array, "source")
        target_array = as_points(target, "target")
        if len(target_array) != len(source_array):
            raise ValueError(
                f"target must have one row per source point: source has "
                f"{len(source_array)}, target has {len(target_array)}")
        self._fit(source_array, target_array, "tps",
                  as_positive(smoothing, "smoothing", allow_zero=True), 0.0)

    def __repr__(self) -> str:
        return (f"TPS(centres={self._model.size}, smoothing={self.smoothing:g}, "
                f"condition_number={self.condition_number:.3g})")

"""Resampling: turn a raw scan into a regular face grid with snapped landmarks.

A raw scan is a point cloud with background and holes (for example a Bosphorus
``.bnt``, about 35k valid points). :func:`resample_scan` drops the invalid points,
resamples x, y onto an H x W grid spanning the valid data and interpolates z
linearly over the valid points, as a Delaunay-based ``griddata`` would, keeping a
validity mask. The result, a :class:`~tpscore.face.grid.FaceGrid`, induces quads (two triangles each)
and a u,v map; its landmarks are snapped to the nearest valid grid vertex.

Two interpolation paths give the same kind of result:

- **Regular source grid** (a ``.bnt``, a depth image): each target point is located
  in its source cell by arithmetic and interpolated linearly on one of the cell's two
  triangles. This is hundreds of times faster than a Delaunay triangulation of the
  same points; :func:`resample_scan` detects the structure automatically.
- **Unstructured point cloud** (mesh vertices, any scattered points): a Delaunay
  triangulation of x, y (``scipy.spatial.Delaunay``), evaluated like
  ``scipy.interpolate.LinearNDInterpolator``.

The grid's conventions (row 0 the largest y, column 0 the smallest x, u,v as in a
``.bnt``) are those of :mod:`tpscore.face.grid`.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay, QhullError

from .._validation import MAX_COORDINATE, as_array, as_positive
from .grid import DEFAULT_GRID_SHAPE, FaceGrid, _as_shape, _default_uv, _snap_landmarks
from .io import BntScan
from .landmarks import as_landmarks, empty_landmarks
from .pose import scan_pose

__all__ = [
    "resample_scan",
    "DEFAULT_MAX_GAP_MM",
]

#: Default widest gap (mm) between valid points that resampling bridges by linear
#: interpolation beyond the scan's own sampling. 3 mm fills scanner dropouts of a
#: few pixels (at the 0.3-0.7 mm spacing of face scanners) without inventing surface
#: over the eye openings, parted lips or real holes, which are wider.
DEFAULT_MAX_GAP_MM = 3.0


# A source grid counts as regular when every valid x (y) lies within this fraction of
# the spacing of x0 + c * sx (y0 + r * sy). Scanner depth images are exact lattices up
# to rounding (float32 files round by ~1e-5 of a 0.7 mm spacing at 100 mm); treating
# them as exact moves a point by at most 1e-4 spacing, far below scanner noise.
# Anything less regular goes the Delaunay way, which makes no such assumption.
_LATTICE_TOLERANCE = 1e-4

# In the unstructured path a Delaunay triangle is always kept when its longest edge is
# at most this many times the median Delaunay edge: irregular (even random) sampling
# has edges up to about twice the median that do not span holes.
_UNSTRUCTURED_EDGE_FACTOR = 3.0


def resample_scan(scan_or_points, landmarks=None, shape=DEFAULT_GRID_SHAPE, *,
                  max_gap_mm: float = DEFAULT_MAX_GAP_MM, uv=None) -> FaceGrid:
    """Resample a raw scan onto a regular H x W face grid and snap its landmarks.

    The grid spans the bounding box of the valid points in x, y: column 0 at the
    smallest x, row 0 at the largest y (as in a ``.bnt``), W and H points evenly
    spaced. z is linear over a triangulation of the valid points, as a Delaunay-based
    ``griddata(..., method="linear")`` computes it:

    - regular source grids (a :class:`~tpscore.face.io.BntScan`, an (R, C, 3) depth image,
      or an (n, 3) cloud whose x, y lie on a lattice) are interpolated cell by cell:
      a cell with four valid corners is split along its (r, c)-(r+1, c+1) diagonal;
      a cell with three valid corners uses the triangle they form; a point on a cell
      edge or corner needs only the corners it depends on.
    - other point clouds are triangulated with ``scipy.spatial.Delaunay``.

    Validity mask: a grid vertex is valid only where the interpolating triangle's
    corners are all valid points. So no surface is invented outside the data or
    across a hole, except that gaps up to `max_gap_mm` are bridged first: on a regular
    source grid each missing source point whose nearest valid neighbours along its
    row (or column) are at most `max_gap_mm` apart gets z interpolated linearly between
    them (both directions averaged, weighted by 1 / span); in the unstructured path
    Delaunay triangles whose longest edge exceeds ``max(max_gap_mm, 3 * median
    Delaunay edge)`` are dropped. Gaps wider than `max_gap_mm`, and everything outside the
    data, stay invalid. ``max_gap_mm=0`` bridges nothing beyond the sampling itself.

    Pose and unit: a scan whose landmarks show another frame (its axes swapped, as in a
    profile view or a y-forward, z-up scanner frame) or unit (centimetres, metres) is
    first brought to the canonical frame, looking toward +z with +y up, in millimetres
    (:func:`tpscore.face.pose.scan_pose`); the grid's ``scan_frame`` maps back. A scan
    within 45 degrees of frontal and in millimetres is resampled as it is.

    Landmarks: each finite landmark is snapped to the nearest valid grid vertex
    (3D distance); missing (NaN) landmarks stay missing. A landmark farther than
    :data:`~tpscore.face.grid.LANDMARK_SNAP_WARNING_MM` from every valid vertex still snaps but raises a
    :class:`~tpscore.face.grid.LandmarkSnapWarning` (it probably lies over a hole or outside the scan).

    Parameters
    ----------
    scan_or_points : BntScan, (R, C, 3) array or (n, 3) array, mm
        The scan. In arrays, NaN marks invalid points.
    landmarks : (22, 3) array-like or None
        Landmarks in the scan's frame, NaN rows for missing ones; None: all missing.
    shape : (int, int)
        Output grid (H, W), each >= 2, at most MAX_GRID_VERTICES (1024 x 1024) in all.
    max_gap_mm : float >= 0
        Widest gap bridged by interpolation (see above).
    uv : (R, C, 2) or (n, 2) array-like, optional
        Texture coordinates of the source points (a BntScan brings its own). They are
        interpolated onto the grid; without them the grid's u,v are its normalised
        pixel centres ``((c + 0.5) / W, (r + 0.5) / H)``.

    Returns
    -------
    FaceGrid

    Raises
    ------
    ValueError
        Fewer than 3 valid points, valid points without extent in x or y (or
        collinear), a point beyond +-1e15 mm, a bad `shape` (more than
        :data:`~tpscore.face.grid.MAX_GRID_VERTICES`) or `max_gap_mm`, landmarks not of shape (22, 3), or
        no grid vertex inside the data.
    """
    height, width = _as_shape(shape)
    max_gap_mm = as_positive(max_gap_mm, "max_gap_mm", allow_zero=True)
    grid, valid, source_uv, cloud, cloud_uv = _split_input(scan_or_points, uv)
    landmarks = empty_landmarks() if landmarks is None else as_landmarks(landmarks)

    # Every step from here on reads depth along z and works in millimetres. A scan in
    # another frame (axes swapped, a profile view) or unit is brought into the canonical
    # one, without rounding its coordinates; the grid keeps the way back.
    pose = scan_pose(landmarks)
    scan_frame = None
    if pose is not None and not pose.canonical:
        landmarks = pose.to_canonical(landmarks)
        if grid is not None:
            grid = pose.to_canonical(grid)
        else:
            cloud = pose.to_canonical(cloud)
        scan_frame = pose.transform.inverse()

    # one outlier far out would stretch the grid over it, leaving no vertex on the face,
    # and overflow the lattice indices below: judged on the valid points first
    _check_extent(grid[valid] if grid is not None else cloud)
    grid, valid, source_uv, cloud, cloud_uv, lattice = _source_lattice(grid, valid, source_uv, cloud, cloud_uv)
    x_min, x_max, y_min, y_max = _valid_extent(valid, cloud, lattice)
    if lattice is not None:
        lattice = lattice[0]
    xs = np.linspace(x_min, x_max, width)
    ys = np.linspace(y_max, y_min, height)

    if lattice is not None:
        z, mask, grid_uv = _resample_lattice(grid, valid, source_uv, lattice, xs, ys, max_gap_mm)
    else:
        z, mask, grid_uv = _resample_delaunay(cloud, cloud_uv, xs, ys, max_gap_mm)
    if not mask.any():
        raise ValueError("scan_or_points: no grid vertex lies inside the valid data")
    if grid_uv is None:
        grid_uv = _default_uv(height, width)

    points = np.empty((height, width, 3))
    points[..., 0] = xs[None, :]
    points[..., 1] = ys[:, None]
    points[..., 2] = z
    points[~mask] = np.nan
    snapped, index = _snap_landmarks(points.reshape(-1, 3), mask.reshape(-1), landmarks)
    return FaceGrid(points, mask, grid_uv, snapped, index, scan_frame=scan_frame)


# --------------------------------------------------------------------------- helpers

def _source_lattice(grid, valid, source_uv, cloud, cloud_uv):
    """The source as a regular lattice where it is one (a grid whose rows and columns
    run along y and x, or a cloud or turned depth image whose points lie on a lattice):
    (grid, valid, source_uv, cloud, cloud_uv, lattice), with ``lattice`` (the fit and
    its x, y extent) None and ``grid`` None for an unstructured cloud."""
    lattice = None
    if grid is not None:
        lattice = _fit_lattice(grid, valid)
        if lattice is None:
            cloud = grid[valid]
            cloud_uv = None if source_uv is None else source_uv[valid]
            # a lattice whose rows and columns do not run along y and x (a depth image
            # turned into the canonical frame) is still one
            detected = _cloud_to_lattice(cloud, cloud_uv)
            if detected is not None:
                grid, valid, source_uv, lattice = detected
            else:
                grid = None
    else:
        detected = _cloud_to_lattice(cloud, cloud_uv)
        if detected is not None:
            grid, valid, source_uv, lattice = detected
    return grid, valid, source_uv, cloud, cloud_uv, lattice


def _valid_extent(valid, cloud, lattice) -> tuple:
    """x_min, x_max, y_min, y_max of the valid points; refuses fewer than three or no
    extent in x or y."""
    n_valid = int(np.count_nonzero(valid)) if lattice is not None else len(cloud)
    if n_valid < 3:
        raise ValueError(f"scan_or_points has {n_valid} valid point(s); at least 3 are needed")
    if lattice is not None:
        x_min, x_max, y_min, y_max = lattice[1]
    else:
        x_min, y_min = cloud[:, 0].min(), cloud[:, 1].min()
        x_max, y_max = cloud[:, 0].max(), cloud[:, 1].max()
    if not (x_max > x_min and y_max > y_min):
        raise ValueError(
            "scan_or_points: the valid points have no extent in x or y "
            f"(x in [{x_min}, {x_max}], y in [{y_min}, {y_max}])"
        )
    return x_min, x_max, y_min, y_max


def _split_input(scan_or_points, uv):
    """(grid, valid, grid_uv, cloud, cloud_uv): one of grid or cloud is None."""
    if isinstance(scan_or_points, BntScan):
        if uv is not None:
            raise ValueError("uv: a BntScan brings its own u,v; do not pass uv with it")
        return scan_or_points.points, scan_or_points.valid, scan_or_points.uv, None, None
    array = as_array(scan_or_points, "scan_or_points")
    if array.ndim == 3 and array.shape[2] == 3:
        valid = np.isfinite(array).all(axis=2)
        source_uv = None
        if uv is not None:
            source_uv = as_array(uv, "uv")
            if source_uv.shape != array.shape[:2] + (2,):
                raise ValueError(f"uv must have shape {array.shape[:2] + (2,)}, got {source_uv.shape}")
            if not np.isfinite(source_uv[valid]).all():
                raise ValueError("uv has NaN or infinite values at valid points")
        return array, valid, source_uv, None, None
    if array.ndim == 2 and array.shape[1] == 3:
        keep = np.isfinite(array).all(axis=1)
        cloud_uv = None
        if uv is not None:
            cloud_uv = as_array(uv, "uv")
            if cloud_uv.shape != (len(array), 2):
                raise ValueError(f"uv must have shape ({len(array)}, 2), got {cloud_uv.shape}")
            cloud_uv = cloud_uv[keep]
            if not np.isfinite(cloud_uv).all():
                raise ValueError("uv has NaN or infinite values at valid points")
        return None, None, None, np.ascontiguousarray(array[keep]), cloud_uv
    raise ValueError(
        f"scan_or_points must be a BntScan, an (R, C, 3) grid or an (n, 3) point array, got shape {array.shape}"
    )


def _fit_line(index: np.ndarray, values: np.ndarray):
    """(origin, step) of values = origin + step * index when that holds to the lattice
    tolerance, else None."""
    if index.min() == index.max():
        return None
    mean_index, mean_value = index.mean(), values.mean()
    centred = index - mean_index
    # einsum rather than np.dot: a BLAS call may wake a thread pool, which on a busy
    # machine costs tens of milliseconds for this microsecond sum.
    step = float(np.einsum("i,i->", centred, values - mean_value) / np.einsum("i,i->", centred, centred))
    origin = float(mean_value - step * mean_index)
    if step == 0.0:
        return None
    residual = np.abs(values - (origin + step * index)).max()
    return (origin, step) if residual <= _LATTICE_TOLERANCE * abs(step) else None


def _fit_lattice(grid: np.ndarray, valid: np.ndarray):
    """((x0, sx, y0, sy), (x_min, x_max, y_min, y_max)) when x = x0 + sx * c and
    y = y0 + sy * r at every valid point, else None. The extents are those of the
    valid points."""
    if min(valid.shape) < 2 or valid.sum() < 3:
        return None
    rows, cols = np.nonzero(valid)
    x, y = grid[rows, cols, 0], grid[rows, cols, 1]
    fit_x = _fit_line(cols.astype(np.float64), x)
    if fit_x is None:
        return None
    fit_y = _fit_line(rows.astype(np.float64), y)
    if fit_y is None:
        return None
    return fit_x + fit_y, (x.min(), x.max(), y.min(), y.max())


def _check_extent(points: np.ndarray) -> None:
    extent = np.abs(points).max() if points.size else 0.0
    if extent > MAX_COORDINATE:
        raise ValueError(f"scan_or_points has a point {extent:.3g} mm from the origin, beyond the "
                         f"+-{MAX_COORDINATE:.0e} mm tpscore accepts (an outlier, or not millimetres?)")


def _lattice_steps(values: np.ndarray):
    """Integer lattice index of each value and the step, or None."""
    unique = np.unique(values)
    if len(unique) < 2:
        return None
    step = float(np.diff(unique).min())
    position = (values - unique[0]) / step
    index = np.rint(position)
    if np.abs(position - index).max() > _LATTICE_TOLERANCE:
        return None
    if index.max() > 2**31:
        return None  # a step tiny against the range: no lattice (and no int64 index)
    return index.astype(np.int64), step


def _cloud_to_lattice(cloud: np.ndarray, cloud_uv):
    """Scatter an (n, 3) cloud whose x, y lie on a lattice into a grid, or None.

    Returns (grid, valid, grid_uv, lattice) in the .bnt orientation (row 0 = largest y).
    """
    n = len(cloud)
    # A lattice of n points has far fewer distinct x than points; this rejects
    # scattered clouds after one np.unique.
    if n < 16 or len(np.unique(cloud[:, 0])) > n // 2:
        return None
    columns = _lattice_steps(cloud[:, 0])
    rows = _lattice_steps(-cloud[:, 1])
    if columns is None or rows is None:
        return None
    (col, _), (row, _) = columns, rows
    n_rows, n_cols = int(row.max()) + 1, int(col.max()) + 1
    # A sparse lattice (mostly empty cells) gains nothing over Delaunay.
    if n_rows * n_cols > 20 * n or n_rows < 2 or n_cols < 2:
        return None
    flat = row * n_cols + col
    if len(np.unique(flat)) != n:
        return None  # two points share an x, y position
    grid = np.full((n_rows, n_cols, 3), np.nan)
    grid.reshape(-1, 3)[flat] = cloud
    valid = np.zeros((n_rows, n_cols), dtype=bool)
    valid.reshape(-1)[flat] = True
    grid_uv = None
    if cloud_uv is not None:
        grid_uv = np.full((n_rows, n_cols, 2), np.nan)
        grid_uv.reshape(-1, 2)[flat] = cloud_uv
    lattice = _fit_lattice(grid, valid)
    if lattice is None:
        return None
    return grid, valid, grid_uv, lattice


def _fill_gaps(z: np.ndarray, valid: np.ndarray, step_x: float, step_y: float, max_gap_mm: float):
    """Bridge gaps of at most max_gap_mm along rows and columns of a depth grid.

    A missing point gets z interpolated linearly between its nearest valid neighbours
    to the left and right (span = their distance), and between those above and below;
    spans wider than max_gap_mm are ignored; the estimates are averaged with weights
    1 / span. A point without valid neighbours on both sides is outside the data and
    stays missing. Linear, so a plane is filled exactly.
    """
    total = np.zeros(z.shape)
    weight = np.zeros(z.shape)
    for axis, step in ((1, step_x), (0, step_y)):
        moved_z, moved_valid = (z, valid) if axis == 1 else (z.T, valid.T)
        n = moved_valid.shape[1]
        position = np.arange(n)
        before = np.maximum.accumulate(np.where(moved_valid, position, -1), axis=1)
        after = np.minimum.accumulate(np.where(moved_valid, position, n)[:, ::-1], axis=1)[:, ::-1]
        span = (after - before) * step
        candidate = ~moved_valid & (before >= 0) & (after < n) & (span <= max_gap_mm)
        lines, cells = np.nonzero(candidate)
        if len(lines) == 0:
            continue
        first, last = before[lines, cells], after[lines, cells]
        t = (cells - first) / (last - first)
        estimate = moved_z[lines, first] + t * (moved_z[lines, last] - moved_z[lines, first])
        w = 1.0 / span[lines, cells]
        if axis == 0:
            lines, cells = cells, lines
        total[lines, cells] += w * estimate
        weight[lines, cells] += w
    filled = weight > 0
    if not filled.any():
        return z, valid
    z = z.copy()
    z[filled] = total[filled] / weight[filled]
    return z, valid | filled


def _cell_coordinate(target: np.ndarray, origin: float, step: float, n: int):
    """Cell index (clamped to [0, n-2]), local coordinate in [0, 1] and in-range flag."""
    position = (target - origin) / step
    # Targets at the data's extremes sit on source nodes up to rounding; put them
    # exactly there so a node on the outline does not look like it is outside.
    nearest = np.rint(position)
    position = np.where(np.abs(position - nearest) <= _LATTICE_TOLERANCE, nearest, position)
    inside = (position >= 0) & (position <= n - 1)
    cell = np.clip(np.floor(position), 0, n - 2).astype(np.int64)
    return cell, position - cell, inside


def _resample_lattice(grid, valid, source_uv, lattice, xs, ys, max_gap_mm):
    """z, mask and u,v on the target axes from a regular source grid (see resample_scan)."""
    x0, step_x, y0, step_y = lattice
    n_rows, n_cols = valid.shape
    z = grid[..., 2]
    if max_gap_mm > 0:
        z, valid = _fill_gaps(z, valid, abs(step_x), abs(step_y), max_gap_mm)
    col, u, col_in = _cell_coordinate(xs, x0, step_x, n_cols)
    row, v, row_in = _cell_coordinate(ys, y0, step_y, n_rows)
    u, v = u[None, :], v[:, None]
    a = row[:, None] * n_cols + col[None, :]          # corner (r, c); b = a + 1,
    corners = (a, a + 1, a + n_cols, a + n_cols + 1)  # c = a + C, d = a + C + 1
    z_flat = np.where(valid, z, 0.0).reshape(-1)      # 0 * NaN would poison the sums
    valid_flat = valid.reshape(-1)
    corner_valid = [valid_flat[k] for k in corners]

    # Split along the a-d diagonal: triangle a,b,d when u >= v, else a,c,d.
    upper = u >= v
    weights_ad = (np.where(upper, 1 - u, 1 - v), np.where(upper, u - v, 0.0),
                  np.where(upper, 0.0, v - u), np.where(upper, v, u))
    # Split along the b-c diagonal: triangle a,b,c when u + v <= 1, else b,c,d.
    lower = u + v <= 1
    weights_bc = (np.where(lower, 1 - u - v, 0.0), np.where(lower, u, 1 - v),
                  np.where(lower, v, 1 - u), np.where(lower, 0.0, u + v - 1))

    def usable(weights):
        # A corner with (up to rounding) zero weight need not be valid: the point is on
        # the opposite edge, for example on the outline of the data.
        ok = np.ones(a.shape, dtype=bool)
        for w, ok_corner in zip(weights, corner_valid):
            ok &= (w <= _LATTICE_TOLERANCE) | ok_corner
        return ok

    use_ad = usable(weights_ad)
    use_bc = ~use_ad & usable(weights_bc)
    mask = (use_ad | use_bc) & row_in[:, None] & col_in[None, :]
    z_out = np.zeros(a.shape)
    weight_sum = np.zeros(a.shape)
    weights = []
    for w_ad, w_bc, k, ok_corner in zip(weights_ad, weights_bc, corners, corner_valid):
        # Invalid corners carry at most a rounding-sized weight: drop it and renormalise.
        w = np.where(ok_corner, np.where(use_ad, w_ad, w_bc), 0.0)
        z_out += w * z_flat[k]
        weight_sum += w
        weights.append(w)
    z_out[mask] /= weight_sum[mask]
    z_out[~mask] = np.nan

    grid_uv = None
    if source_uv is not None:
        uv_flat = source_uv.reshape(-1, 2)
        if np.isfinite(uv_flat).all():
            # u,v known at every source pixel (a .bnt has them at background too):
            # bilinear over the whole cell, exact for the affine u,v of a depth image.
            # One contiguous channel at a time keeps the gathers cheap.
            bilinear = ((1 - u) * (1 - v), u * (1 - v), (1 - u) * v, u * v)
            grid_uv = np.empty(a.shape + (2,))
            for channel in range(2):
                values = np.ascontiguousarray(uv_flat[:, channel])
                grid_uv[..., channel] = sum(w * values[k] for w, k in zip(bilinear, corners))
        else:
            # u,v only at some points: the z weights over the corners that have them.
            known = np.isfinite(uv_flat).all(axis=1)
            safe_uv = np.where(known[:, None], uv_flat, 0.0)
            total, uv_sum = np.zeros(a.shape), np.zeros(a.shape + (2,))
            for w, k in zip(weights, corners):
                w = np.where(known[k], w, 0.0)
                uv_sum += w[..., None] * safe_uv[k]
                total += w
            grid_uv = _default_uv(*a.shape)
            has = total > 0
            grid_uv[has] = uv_sum[has] / total[has][:, None]
    return z_out, mask, grid_uv


def _resample_delaunay(cloud, cloud_uv, xs, ys, max_gap_mm):
    """z, mask and u,v on the target axes from scattered points (see resample_scan)."""

    xy = np.ascontiguousarray(cloud[:, :2])
    try:
        triangulation = Delaunay(xy)
    except QhullError as exc:
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise ValueError(
            f"scan_or_points: the valid points cannot be triangulated in x, y "
            f"(collinear or coincident?): {first_line}"
        ) from None
    height, width = len(ys), len(xs)
    targets = np.empty((height * width, 2))
    targets[:, 0] = np.tile(xs, height)
    targets[:, 1] = np.repeat(ys, width)
    simplex = triangulation.find_simplex(targets)

    # Drop triangles that bridge gaps wider than the sampling and max_gap_mm allow.
    corners = xy[triangulation.simplices]
    edges = np.linalg.norm(corners - corners[:, [1, 2, 0]], axis=2)
    spacing = float(np.median(edges))
    allowed = edges.max(axis=1) <= max(max_gap_mm, _UNSTRUCTURED_EDGE_FACTOR * spacing)
    found = simplex >= 0
    found[found] = allowed[simplex[found]]

    hit = simplex[found]
    transform = triangulation.transform[hit]
    barycentric = np.einsum("nij,nj->ni", transform[:, :2], targets[found] - transform[:, 2])
    weights = np.column_stack([barycentric, 1.0 - barycentric.sum(axis=1)])
    vertex = triangulation.simplices[hit]
    z = np.full(height * width, np.nan)
    z[found] = np.einsum("nk,nk->n", weights, cloud[vertex, 2])
    grid_uv = None
    if cloud_uv is not None:
        grid_uv = _default_uv(height, width).reshape(-1, 2)
        grid_uv[found] = np.einsum("nk,nkj->nj", weights, cloud_uv[vertex])
        grid_uv = grid_uv.reshape(height, width, 2)
    return z.reshape(height, width), found.reshape(height, width), grid_uv

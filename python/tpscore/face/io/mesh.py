"""Meshes and point clouds: :func:`read_mesh` (any format trimesh reads; OBJ parsed
directly) and :func:`write_mesh` (OBJ or PLY, with u,v and vertex colours)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..._files import atomic_write, check_readable, open_for_reading, regular_file_size
from ..._validation import as_faces, as_path, as_points
from ._common import MAX_MESH_FILE_BYTES
from .obj import _obj_bytes, _read_obj
from .ply import _ply_bytes


def read_mesh(path):
    """Read a mesh or point cloud with trimesh, keeping the file's vertex order.

    Any format trimesh reads (OBJ, PLY, STL, OFF, GLB, ...). A scene of several
    geometries is concatenated (with their scene transforms applied).

    Returns
    -------
    vertices : (n, 3) float64, mm
    faces : (m, 3) int64; (0, 3) for a point cloud

    Raises
    ------
    ValueError
        If the file is missing, unreadable, or holds no vertices.
    """
    # trimesh takes a third of a second to import; only mesh files need it
    import trimesh

    path = check_readable(path)
    where = repr(str(path))
    if path.suffix.lower() == ".obj":
        # trimesh drops OBJ vertices no face uses once texture coordinates are present,
        # which would break the correspondence with the file's vertex order.
        return _read_obj(path)
    with open_for_reading(path) as handle:
        size = regular_file_size(handle)
    if size is None:
        raise ValueError(f"{where}: not a regular file (trimesh reads meshes from files only)")
    if size > MAX_MESH_FILE_BYTES:
        raise ValueError(f"{where}: the file is {size:,} bytes; tpscore reads meshes of at most "
                         f"{MAX_MESH_FILE_BYTES:,}")
    try:
        # process=False keeps the vertex order (no merging); fix_texture=False stops the
        # PLY reader from splitting vertices along u,v seams.
        loaded = trimesh.load(str(path), process=False, fix_texture=False)
    except Exception as exc:  # trimesh raises many types for unreadable input
        raise ValueError(f"{where}: cannot be read as a mesh or point cloud ({type(exc).__name__}: {exc})") from None
    if isinstance(loaded, trimesh.Scene):
        geometries = list(loaded.geometry.values())
        if not geometries:
            raise ValueError(f"{where}: the file holds no geometry")
        loaded = loaded.to_geometry() if hasattr(loaded, "to_geometry") else loaded.dump(concatenate=True)
    vertices = np.ascontiguousarray(np.asarray(getattr(loaded, "vertices", np.empty((0, 3))), dtype=np.float64))
    faces = getattr(loaded, "faces", None)
    faces = np.empty((0, 3), dtype=np.int64) if faces is None else np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise ValueError(f"{where}: the file holds no vertices")
    if not np.isfinite(vertices).all():
        raise ValueError(f"{where}: the file has NaN or infinite vertex coordinates")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        # trimesh (with process=False) passes a PLY's indices through unchecked
        bad = int(faces[(faces < 0) | (faces >= len(vertices))][0])
        raise ValueError(f"{where}: a face refers to vertex {bad}, but the file has vertices 0 to "
                         f"{len(vertices) - 1}")
    return vertices, np.ascontiguousarray(faces)


def _colors_uint8(vertex_colors, n: int) -> np.ndarray:
    colors = np.asarray(vertex_colors)
    if colors.ndim != 2 or colors.shape[0] != n or colors.shape[1] not in (3, 4):
        raise ValueError(f"vertex_colors must have shape ({n}, 3) or ({n}, 4), got {colors.shape}")
    if np.issubdtype(colors.dtype, np.floating):
        if not np.isfinite(colors).all() or colors.min() < 0 or colors.max() > 1:
            raise ValueError("float vertex_colors must lie in [0, 1]")
        colors = np.round(colors * 255.0)
    elif not np.issubdtype(colors.dtype, np.integer) or colors.min() < 0 or colors.max() > 255:
        raise ValueError("integer vertex_colors must lie in [0, 255]")
    colors = colors.astype(np.uint8)
    if colors.shape[1] == 3:
        colors = np.concatenate([colors, np.full((n, 1), 255, np.uint8)], axis=1)
    return colors


def write_mesh(path, vertices, faces, *, uv=None, vertex_colors=None) -> None:
    """Write a triangle mesh (or, with no faces, a point cloud) as ``.obj`` or ``.ply``.

    Parameters
    ----------
    path : str or PathLike
        ``.obj`` (text) or ``.ply`` (binary little-endian, float64 coordinates).
    vertices : (n, 3) array-like, mm, all finite (drop masked vertices first, for
        example with :meth:`tpscore.face.grid.FaceGrid.mesh`).
    faces : (m, 3) integer array-like (m may be 0).
    uv : (n, 2) array-like, optional
        Per-vertex texture coordinates, written as given: OBJ ``vt`` lines with
        ``f v/vt`` faces, PLY ``texture_u``/``texture_v`` vertex properties. Viewers take
        v = 0 at the bottom of the image; pass ``1 - v`` for image-row coordinates such
        as those of a ``.bnt``.
    vertex_colors : (n, 3) or (n, 4), optional
        uint8 in [0, 255] or float in [0, 1]: OBJ ``v x y z r g b``, PLY red/green/blue/alpha.
    """

    vertices = as_points(vertices, "vertices")
    faces = as_faces(np.asarray(faces).reshape(-1, 3) if np.size(faces) == 0 else faces, len(vertices))
    n = len(vertices)
    if uv is not None:
        uv = as_points(uv, "uv", dim=2)
        if len(uv) != n:
            raise ValueError(f"uv must have shape ({n}, 2), got {uv.shape}")
    if n >= 2**31:
        raise ValueError(f"write_mesh stores vertex indices as int32; {n} vertices are too many")
    colors = None if vertex_colors is None else _colors_uint8(vertex_colors, n)
    suffix = Path(as_path(path)).suffix.lower()
    if suffix == ".obj":
        data = _obj_bytes(vertices, faces, uv, colors)
    elif suffix == ".ply":
        data = _ply_bytes(vertices, faces, uv, colors)
    else:
        raise ValueError(f"{str(path)!r}: write_mesh writes .obj or .ply, not {suffix!r}")
    atomic_write(path, data)

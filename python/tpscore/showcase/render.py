"""Headless pictures of face meshes: a compiled z-buffer rasteriser and Pillow output.

No display and no OpenGL: meshes are projected orthographically, looking down -z (the
face looks toward +z, so the viewer sees it from the front with the subject's left on
the viewer's right), rasterised with a z-buffer (:mod:`tpscore.raster`), and shaded with Lambert
diffuse, Blinn-Phong specular and ambient light from interpolated vertex normals. A
surface is clay-coloured, coloured per vertex, or textured by a scan's colour image
(looked up per pixel at the interpolated u,v, so the picture keeps the image's detail
between the vertices). :func:`motion_map` draws a displacement field as colours and
arrows on the face it moves.

A :class:`Camera` fixes the view direction and the framing (centre and scale); build
one with :func:`fit_camera` over several meshes so that side-by-side pictures line up.
Pillow writes PNG and animated GIF files and draws titles and colour bars.
"""
from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw

from .._files import atomic_write
from .._validation import as_faces, as_points
from ..face.image import as_colour_image, sample_image
from ..raster import rasterise

__all__ = [
    "Camera",
    "VIEWS",
    "fit_camera",
    "render_mesh",
    "grid_mesh",
    "render_grid",
    "heatmap_colors",
    "draw_colorbar",
    "error_heatmap",
    "motion_map",
    "side_by_side",
    "save_png",
    "save_gif",
]

#: Named views: yaw in degrees of the face about the vertical axis before projection
#: (positive turns the subject's left side toward the viewer).
VIEWS = {
    "front": 0.0,
    "left": -90.0,            # the subject's left profile
    "right": 90.0,
    "three_quarter_left": -35.0,
    "three_quarter_right": 35.0,
}

DEFAULT_BACKGROUND = (255, 255, 255)
DEFAULT_SURFACE_COLOR = (0.86, 0.78, 0.70)   # a light clay, neutral under any light
# Light from the upper left of the viewer and in front, so the nose casts its shading
# to the lower right and the brows shade the eyes, as in a studio portrait.
DEFAULT_LIGHT = (-0.35, 0.45, 1.0)
AMBIENT = 0.18
DIFFUSE = 0.72
SPECULAR = 0.12
SHININESS = 24.0
# A photograph's colours already hold the light of the scanner, so a textured surface
# gets more ambient and less directional light than clay: enough shading to show the
# shape from the new view, without darkening the photograph's own shadows twice.
TEXTURE_AMBIENT = 0.5
TEXTURE_DIFFUSE = 0.55
TEXTURE_SPECULAR = 0.05
MISSING_VALUE_COLOR = (0.6, 0.6, 0.6)
FRAME_MARGIN = 0.06          # fraction of the picture left free around the framed meshes
COLORBAR_WIDTH = 70

# Anchors of a perceptually ordered dark-blue -> green -> yellow map, in the spirit
# of viridis: lightness rises monotonically from the first to the last.
_VIRIDIS_LIKE = np.array([
    [0.267, 0.005, 0.329],
    [0.229, 0.322, 0.546],
    [0.128, 0.567, 0.551],
    [0.369, 0.789, 0.383],
    [0.993, 0.906, 0.144],
])
_GRAY = np.array([[0.1, 0.1, 0.1], [0.95, 0.95, 0.95]])
# Blue -> white -> red for signed values.
_DIVERGING = np.array([[0.23, 0.30, 0.75], [0.87, 0.87, 0.87], [0.71, 0.02, 0.15]])
COLORMAPS = {"viridis": _VIRIDIS_LIKE, "gray": _GRAY, "diverging": _DIVERGING}


@dataclass(frozen=True)
class Camera:
    """Orthographic camera.

    Attributes
    ----------
    rotation : (3, 3) float64
        Applied to the vertices before projection (view space: x right, y up, z toward
        the viewer).
    center : (2,) float64
        View-space x, y (mm) shown at the picture centre.
    scale : float
        Pixels per mm.
    width, height : int
        Picture size in pixels.
    """

    rotation: np.ndarray
    center: np.ndarray
    scale: float
    width: int
    height: int

    def to_view(self, vertices: np.ndarray) -> np.ndarray:
        return vertices @ self.rotation.T

    def to_pixels(self, view_points: np.ndarray) -> np.ndarray:
        """(n, 2) continuous pixel coordinates (column, row) of view-space points."""
        col = (view_points[:, 0] - self.center[0]) * self.scale + self.width / 2
        row = self.height / 2 - (view_points[:, 1] - self.center[1]) * self.scale
        return np.column_stack([col, row])


def _view_rotation(view) -> np.ndarray:
    if isinstance(view, str):
        if view not in VIEWS:
            raise ValueError(f"view must be one of {', '.join(VIEWS)} or a (3, 3) rotation, got {view!r}")
        yaw = np.radians(VIEWS[view])
        c, s = np.cos(yaw), np.sin(yaw)
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    rotation = np.asarray(view, dtype=np.float64)
    if rotation.shape != (3, 3) or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6):
        raise ValueError("view must be a view name or a (3, 3) rotation matrix")
    return rotation


def _check_size(width, height):
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= value <= 8192:
            raise ValueError(f"{name} must be an integer in [1, 8192], got {value!r}")
    return int(width), int(height)


def fit_camera(meshes, *, width: int = 400, height: int = 400, view="front",
               margin: float = FRAME_MARGIN) -> Camera:
    """A camera framing every vertex of every mesh, for pictures that line up.

    Parameters
    ----------
    meshes : sequence of (n, 3) array_like
        Vertex arrays (NaN rows are ignored).
    width, height : int
        Picture size in pixels.
    view : str or (3, 3) array
        A name from ``VIEWS`` or a rotation into view space.
    margin : float
        Fraction of the picture kept free on each side.
    """
    width, height = _check_size(width, height)
    rotation = _view_rotation(view)
    if isinstance(meshes, np.ndarray) and meshes.ndim == 2:
        meshes = [meshes]
    stacked = [np.asarray(m, dtype=np.float64).reshape(-1, 3) for m in meshes]
    points = np.concatenate(stacked) if stacked else np.zeros((0, 3))
    points = points[np.isfinite(points).all(axis=1)] @ rotation.T
    if len(points) == 0:
        return Camera(rotation, np.zeros(2), 1.0, width, height)
    low, high = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    extent = np.maximum(high - low, 1e-9)
    usable = 1.0 - 2.0 * margin
    scale = min(width * usable / extent[0], height * usable / extent[1])
    return Camera(rotation, (low + high) / 2, float(scale), width, height)


def _vertex_normals(view_vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, oriented toward the viewer (+z)."""
    corners = view_vertices[faces]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    # Flip triangles wound away from the viewer so that lighting does not depend on
    # the winding convention of the caller's mesh.
    face_normals *= np.where(face_normals[:, 2:3] < 0, -1.0, 1.0)
    normals = np.zeros_like(view_vertices)
    flat = faces.ravel()
    for axis in range(3):
        normals[:, axis] = np.bincount(flat, weights=np.repeat(face_normals[:, axis], 3),
                                       minlength=len(view_vertices))
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)


def _as_color(color, name) -> np.ndarray:
    array = np.asarray(color, dtype=np.float64).reshape(-1)
    if array.shape != (3,) or not np.isfinite(array).all():
        raise ValueError(f"{name} must be an RGB triple, got {color!r}")
    if array.max() > 1.0:   # 0-255 given
        array = array / 255.0
    return np.clip(array, 0.0, 1.0)


def _vertex_colors(colors, n_vertices: int) -> np.ndarray:
    """(n, 3) RGB in [0, 1] from None, one RGB triple, per-vertex scalars or per-vertex RGB."""
    if colors is None:
        return np.tile(DEFAULT_SURFACE_COLOR, (n_vertices, 1))
    array = np.asarray(colors, dtype=np.float64)
    if array.shape == (3,) and n_vertices != 3:
        return np.tile(_as_color(array, "colors"), (n_vertices, 1))
    if array.ndim == 1 and len(array) == n_vertices:
        return heatmap_colors(array)
    if array.shape == (n_vertices, 3):
        if np.nanmax(array) > 1.0:
            array = array / 255.0
        return np.clip(np.nan_to_num(array, nan=MISSING_VALUE_COLOR[0]), 0.0, 1.0)
    raise ValueError(
        f"colors must be None, an RGB triple, ({n_vertices},) scalars or ({n_vertices}, 3) RGB, "
        f"got shape {array.shape}"
    )


def render_mesh(vertices, faces, *, width: int = 400, height: int = 400, view="front",
                light=DEFAULT_LIGHT, colors=None, background=DEFAULT_BACKGROUND,
                camera: Camera | None = None, texture=None, uv=None) -> np.ndarray:
    """Render a triangle mesh to an RGB picture.

    Parameters
    ----------
    vertices : (n, 3) array_like, mm
        Rows with NaN are allowed; triangles that use them are skipped.
    faces : (m, 3) array_like of int
    width, height : int
        Picture size in pixels (ignored when `camera` is given).
    view : str or (3, 3) array
        A name from ``VIEWS`` or a rotation into view space (ignored with `camera`).
    light : (3,) array_like
        Direction toward the light in view space.
    colors : None, RGB triple, (n,) scalars or (n, 3) RGB
        Surface colour; scalars go through :func:`heatmap_colors`.
    background : RGB triple (0-255 or 0-1)
    camera : Camera, optional
        Shared framing from :func:`fit_camera`; by default the mesh is framed alone.
    texture : (h, w, 3) uint8, optional
        A colour image (a scan's photograph) to paint the surface with, instead of
        `colors`; needs `uv`.
    uv : (n, 2) array_like, optional
        Each vertex's place in `texture` (u right, v down, in [0, 1]).

    Returns
    -------
    (height, width, 3) uint8
    """
    points = as_points(vertices, "vertices", finite=False)
    triangles = as_faces(faces, len(points), "faces")
    finite = np.isfinite(points).all(axis=1)
    triangles = triangles[finite[triangles].all(axis=1)]
    light_dir = np.asarray(light, dtype=np.float64).reshape(-1)
    if light_dir.shape != (3,) or not np.isfinite(light_dir).all() or not np.any(light_dir):
        raise ValueError(f"light must be a non-zero direction (3,), got {light!r}")
    light_dir = light_dir / np.linalg.norm(light_dir)
    back = _as_color(background, "background")
    if texture is not None:
        if colors is not None:
            raise ValueError("give colors or texture, not both")
        if uv is None:
            raise ValueError("texture needs uv, each vertex's place in the image")
        texture = as_colour_image(texture, "texture")
        texture_uv = np.asarray(uv, dtype=np.float64)
        if texture_uv.shape != (len(points), 2) or not np.isfinite(texture_uv[finite]).all():
            raise ValueError(f"uv must be ({len(points)}, 2) and finite at the finite vertices, "
                             f"got shape {texture_uv.shape}")
        texture_uv = np.where(np.isfinite(texture_uv), texture_uv, 0.0)
    elif uv is not None:
        raise ValueError("uv is only used with a texture")
    vertex_rgb = _vertex_colors(colors, len(points))
    if camera is None:
        camera = fit_camera([points[finite]], width=width, height=height, view=view)
    elif not isinstance(camera, Camera):
        raise ValueError(f"camera must be a Camera (see fit_camera), got {type(camera).__name__}")

    safe = np.where(finite[:, None], points, 0.0)
    view_points = camera.to_view(safe)
    pixels = camera.to_pixels(view_points)
    triangle, barycentric = rasterise(pixels, view_points[:, 2], triangles, camera.width, camera.height)
    covered = np.flatnonzero(triangle.reshape(-1) >= 0)
    tri = triangle.reshape(-1)[covered]
    bary = barycentric.reshape(-1, 3)[covered]

    image = np.tile(back, (camera.width * camera.height, 1))
    if len(covered):
        normals = _vertex_normals(view_points, triangles)
        corners = triangles[tri]
        normal = np.einsum("kj,kjd->kd", bary, normals[corners])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        diffuse = np.clip(normal @ light_dir, 0.0, 1.0)
        halfway = light_dir + np.array([0.0, 0.0, 1.0])
        halfway /= np.linalg.norm(halfway)
        specular = np.clip(normal @ halfway, 0.0, 1.0) ** SHININESS
        if texture is None:
            albedo = np.einsum("kj,kjd->kd", bary, vertex_rgb[corners])
            shade = albedo * (AMBIENT + DIFFUSE * diffuse)[:, None] + SPECULAR * specular[:, None]
        else:
            pixel_uv = np.einsum("kj,kjd->kd", bary, texture_uv[corners])
            albedo = sample_image(texture, pixel_uv) / 255.0
            shade = albedo * (TEXTURE_AMBIENT + TEXTURE_DIFFUSE * diffuse)[:, None] \
                + TEXTURE_SPECULAR * specular[:, None]
        image[covered] = np.clip(shade, 0.0, 1.0)
    return np.round(image.reshape(camera.height, camera.width, 3) * 255).astype(np.uint8)


def grid_mesh(points, mask=None) -> tuple[np.ndarray, np.ndarray]:
    """Triangles over a grid of points.

    Parameters
    ----------
    points : (H, W, 3) array_like, NaN where invalid
    mask : (H, W) bool, optional
        Valid vertices (default: the finite ones).

    Returns
    -------
    vertices : (H * W, 3) float64, the grid flattened row after row (invalid rows NaN)
    faces : (m, 3) int64
        Two triangles per quad of four valid corners, and one triangle for a quad with
        exactly three, so the mesh reaches the ragged border of the valid region.
        Wound counter-clockwise seen from +z when rows run toward -y.
    """
    grid = np.asarray(points, dtype=np.float64)
    if grid.ndim != 3 or grid.shape[2] != 3:
        raise ValueError(f"points must have shape (H, W, 3), got {grid.shape}")
    rows, cols = grid.shape[:2]
    valid = np.isfinite(grid).all(axis=2)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (rows, cols):
            raise ValueError(f"mask must have shape {(rows, cols)}, got {mask.shape}")
        valid &= mask
    vertices = grid.reshape(-1, 3).copy()
    vertices[~valid.ravel()] = np.nan
    if rows < 2 or cols < 2:
        return vertices, np.zeros((0, 3), dtype=np.int64)
    index = np.arange(rows * cols).reshape(rows, cols)
    top_left, top_right = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    bottom_left, bottom_right = index[1:, :-1].ravel(), index[1:, 1:].ravel()
    v = valid.ravel()
    tl, tr, bl, br = v[top_left], v[top_right], v[bottom_left], v[bottom_right]
    # Rows go down (toward -y), columns right (+x): (tl, bl, br) is counter-clockwise
    # seen from +z. Each quad is split along tl-br unless that corner pair is missing.
    candidates = [
        (tl & bl & br, (top_left, bottom_left, bottom_right)),
        (tl & br & tr, (top_left, bottom_right, top_right)),
        (tl & bl & tr & ~br, (top_left, bottom_left, top_right)),
        (bl & br & tr & ~tl, (bottom_left, bottom_right, top_right)),
    ]
    faces = [np.column_stack([c[keep] for c in corners]) for keep, corners in candidates]
    return vertices, np.concatenate(faces).astype(np.int64)


def render_grid(points, mask=None, **kwargs) -> np.ndarray:
    """Render a grid face (H, W, 3) with NaN or a mask; keyword arguments as render_mesh.

    Per-vertex `colors` may be given on the grid, (H, W) or (H, W, 3), and so may the
    `uv` of a `texture`, (H, W, 2): a :class:`~tpscore.face.grid.FaceGrid` is drawn in
    its own colours by ``render_grid(grid.points, grid.mask, texture=grid.image,
    uv=grid.uv)``.
    """
    vertices, faces = grid_mesh(points, mask)
    for name in ("colors", "uv"):
        values = kwargs.get(name)
        if values is not None:
            values = np.asarray(values, dtype=np.float64)
            if values.shape[:2] == np.shape(points)[:2]:
                # Per-vertex values given on the grid: flatten like the vertices.
                kwargs[name] = values.reshape((len(vertices),) + values.shape[2:])
    return render_mesh(vertices, faces, **kwargs)


def heatmap_colors(values, vmax: float | None = None, cmap: str = "viridis",
                   vmin: float | None = None) -> np.ndarray:
    """Per-vertex RGB (n, 3) in [0, 1] for scalar values.

    Values are mapped linearly from [vmin, vmax] (default [0, max]; for the
    "diverging" map [-max|v|, max|v|]) onto the colour map and clipped; NaN is grey.
    """
    if cmap not in COLORMAPS:
        raise ValueError(f"cmap must be one of {', '.join(COLORMAPS)}, got {cmap!r}")
    data = np.asarray(values, dtype=np.float64).reshape(-1)
    finite = np.isfinite(data)
    if vmin is None:
        vmin = -np.max(np.abs(data[finite]), initial=0.0) if cmap == "diverging" else 0.0
    if vmax is None:
        vmax = np.max(np.abs(data[finite]), initial=0.0) if cmap == "diverging" \
            else np.max(data[finite], initial=0.0)
    if not (np.isfinite(vmin) and np.isfinite(vmax)):
        raise ValueError(f"vmin and vmax must be finite, got {vmin!r}, {vmax!r}")
    span = vmax - vmin if vmax > vmin else 1.0
    t = np.clip((np.where(finite, data, vmin) - vmin) / span, 0.0, 1.0)
    anchors = COLORMAPS[cmap]
    position = t * (len(anchors) - 1)
    lower = np.minimum(np.floor(position).astype(np.int64), len(anchors) - 2)
    fraction = (position - lower)[:, None]
    rgb = anchors[lower] * (1.0 - fraction) + anchors[lower + 1] * fraction
    rgb[~finite] = MISSING_VALUE_COLOR
    return rgb


def _to_pil(image):

    array = np.asarray(image)
    if array.ndim != 3 or array.shape[2] != 3 or array.dtype != np.uint8:
        raise ValueError(f"image must be an (H, W, 3) uint8 array, got {array.shape} {array.dtype}")
    return Image.fromarray(array, "RGB")


def draw_colorbar(image, vmin: float, vmax: float, *, cmap: str = "viridis",
                  unit: str = "mm", width: int = COLORBAR_WIDTH) -> np.ndarray:
    """Append a vertical colour bar with its value range to the right of `image`."""

    picture = np.asarray(image)
    height = picture.shape[0]
    panel = np.full((height, width, 3), 255, dtype=np.uint8)
    top, bottom = int(0.12 * height), int(0.88 * height)
    bar_left, bar_right = 8, max(9, width // 3)
    ramp = np.linspace(1.0, 0.0, max(bottom - top, 1))
    colors = heatmap_colors(ramp, vmax=1.0, vmin=0.0, cmap=cmap)
    panel[top:bottom, bar_left:bar_right] = np.round(colors * 255).astype(np.uint8)[:, None, :]
    canvas = _to_pil(np.ascontiguousarray(np.concatenate([picture, panel], axis=1)))
    draw = ImageDraw.Draw(canvas)
    x_text = picture.shape[1] + bar_right + 4
    draw.rectangle([picture.shape[1] + bar_left - 1, top - 1, picture.shape[1] + bar_right, bottom],
                   outline=(0, 0, 0))
    draw.text((x_text, top - 6), f"{vmax:.2f}", fill=(0, 0, 0))
    draw.text((x_text, bottom - 6), f"{vmin:.2f}", fill=(0, 0, 0))
    draw.text((picture.shape[1] + bar_left, max(top - 22, 0)), unit, fill=(0, 0, 0))
    return np.asarray(canvas)


def error_heatmap(vertices, faces, errors_mm, *, vmax: float | None = None, width: int = 400,
                  height: int = 400, view="front", camera: Camera | None = None,
                  cmap: str = "viridis", background=DEFAULT_BACKGROUND) -> np.ndarray:
    """Render per-vertex errors (mm) as colours on the shaded mesh, with a colour bar.

    The picture is (height, width, 3): the mesh is drawn in the left part and the
    colour bar (range 0 to vmax, default the largest error; -vmax to vmax for the
    "diverging" map) in the right part. A given `camera` frames the mesh part; the
    picture is then COLORBAR_WIDTH pixels wider than the camera's.
    """
    errors = np.asarray(errors_mm, dtype=np.float64).reshape(-1)
    points = as_points(vertices, "vertices", finite=False)
    if len(errors) != len(points):
        raise ValueError(f"errors_mm must have one value per vertex ({len(points)}), got {len(errors)}")
    if vmax is None:
        vmax = float(np.nanmax(errors)) if np.isfinite(errors).any() else 1.0
    vmin = -vmax if cmap == "diverging" else 0.0
    width, height = _check_size(width, height)
    mesh_width = max(width - COLORBAR_WIDTH, 1)
    if camera is None:
        finite = np.isfinite(points).all(axis=1)
        camera = fit_camera([points[finite]], width=mesh_width, height=height, view=view)
    colors = heatmap_colors(errors, vmax=vmax, vmin=vmin, cmap=cmap)
    picture = render_mesh(points, faces, colors=colors, camera=camera, background=background)
    return draw_colorbar(picture, vmin, vmax, cmap=cmap)


def motion_map(vertices, faces, displacement, *, vmax: float | None = None, width: int = 400,
               height: int = 400, view="front", camera: Camera | None = None,
               arrow_spacing: int = 22, background=DEFAULT_BACKGROUND) -> np.ndarray:
    """A displacement field on the face it moves: its size as colours, its direction as
    arrows, with a colour bar.

    Parameters
    ----------
    vertices : (n, 3) array_like, mm
        The face at rest (NaN rows allowed).
    faces : (m, 3) array_like of int
    displacement : (n, 3) array_like, mm
        Each vertex's motion (NaN where unknown: drawn grey, without an arrow).
    vmax : float, optional
        The size at the top of the colour bar (default the largest).
    width, height, view, camera, background
        As in :func:`error_heatmap` (the colour bar takes COLORBAR_WIDTH pixels).
    arrow_spacing : int
        Pixels between arrows. Arrows start at the vertex nearest each node of a
        square lattice of this spacing and show the motion seen from the camera,
        lengthened by one factor for the whole picture (written in its lower left
        corner) so that the longest arrows are about as long as the spacing. Motion
        under a tenth of the largest, and arrows shorter than 5 pixels, are not drawn.

    Returns
    -------
    (height, width, 3) uint8
    """
    points = as_points(vertices, "vertices", finite=False)
    motion = np.asarray(displacement, dtype=np.float64)
    if motion.shape != points.shape:
        raise ValueError(f"displacement must have shape {points.shape}, like vertices; got {motion.shape}")
    if isinstance(arrow_spacing, bool) or not isinstance(arrow_spacing, (int, np.integer)) \
            or not 4 <= arrow_spacing <= 200:
        raise ValueError(f"arrow_spacing must be an integer in [4, 200] pixels, got {arrow_spacing!r}")
    size = np.linalg.norm(motion, axis=1)
    known = np.isfinite(size) & np.isfinite(points).all(axis=1)
    if vmax is None:
        vmax = float(size[known].max()) if known.any() else 1.0
    if not (np.isfinite(vmax) and vmax > 0):
        vmax = 1.0
    width, height = _check_size(width, height)
    if camera is None:
        camera = fit_camera([points[known]], width=max(width - COLORBAR_WIDTH, 1), height=height, view=view)
    colors = heatmap_colors(np.where(known, size, np.nan), vmax=vmax, vmin=0.0)
    picture = render_mesh(points, faces, colors=colors, camera=camera, background=background)

    start = camera.to_pixels(camera.to_view(np.where(known[:, None], points, 0.0)))
    shift = camera.to_view(np.where(known[:, None], motion, 0.0))[:, :2] * camera.scale * [1.0, -1.0]
    shown = known & (size > 0.1 * vmax)
    canvas = _to_pil(np.ascontiguousarray(picture))
    draw = ImageDraw.Draw(canvas)
    if shown.any():
        # one arrow per lattice cell: the vertex nearest the cell's centre
        cell = np.floor(start[shown] / arrow_spacing).astype(np.int64)
        centre = (cell + 0.5) * arrow_spacing
        candidates = np.flatnonzero(shown)
        order = np.lexsort((np.linalg.norm(start[shown] - centre, axis=1), cell[:, 1], cell[:, 0]))
        first = np.ones(len(order), dtype=bool)
        first[1:] = (np.diff(cell[order], axis=0) != 0).any(axis=1)
        chosen = candidates[order[first]]
        longest = np.percentile(np.linalg.norm(shift[chosen], axis=1), 95)
        gain = 0.9 * arrow_spacing / longest if longest > 0 else 1.0
        for k in chosen:
            _arrow(draw, start[k], start[k] + gain * shift[k])
        draw.text((6, camera.height - 16), f"arrows {gain:.1f}x the motion", fill=(0, 0, 0))
    return draw_colorbar(np.asarray(canvas), 0.0, vmax)


def _arrow(draw, tail, head) -> None:
    """A black arrow with a light halo, so it shows on every colour of the map."""
    vector = np.asarray(head) - np.asarray(tail)
    length = float(np.hypot(*vector))
    if length < 5.0:   # shorter arrows are blots, not directions
        return
    direction = vector / length
    barb = min(5.0, 0.4 * length)
    normal = np.array([-direction[1], direction[0]])
    wings = [tuple(head - barb * direction + side * 0.6 * barb * normal) for side in (1, -1)]
    line = [tuple(tail), tuple(head)]
    for colour, line_width in (((255, 255, 255), 3), ((0, 0, 0), 1)):
        draw.line(line, fill=colour, width=line_width)
        for wing in wings:
            draw.line([tuple(head), wing], fill=colour, width=line_width)


def side_by_side(images, titles=None, *, title_height: int = 24, gap: int = 6,
                 background=DEFAULT_BACKGROUND) -> np.ndarray:
    """Place pictures left to right (top-aligned) with a title above each."""

    pictures = [np.asarray(image) for image in images]
    if not pictures:
        raise ValueError("images is empty; at least one picture is needed")
    for picture in pictures:
        _to_pil(picture)  # validates shape and dtype
    if titles is not None and len(titles) != len(pictures):
        raise ValueError(f"titles must have one entry per image ({len(pictures)}), got {len(titles)}")
    top = title_height if titles is not None else 0
    total_width = sum(p.shape[1] for p in pictures) + gap * (len(pictures) - 1)
    total_height = top + max(p.shape[0] for p in pictures)
    back = np.round(_as_color(background, "background") * 255).astype(np.uint8)
    canvas = np.tile(back, (total_height, total_width, 1))
    offsets = []
    x = 0
    for picture in pictures:
        canvas[top:top + picture.shape[0], x:x + picture.shape[1]] = picture
        offsets.append(x)
        x += picture.shape[1] + gap
    result = _to_pil(canvas)
    if titles is not None:
        draw = ImageDraw.Draw(result)
        for title, offset, picture in zip(titles, offsets, pictures):
            text = str(title)
            text_width = draw.textlength(text)
            draw.text((offset + max((picture.shape[1] - text_width) / 2, 2), 6), text, fill=(0, 0, 0))
    return np.asarray(result)


def save_png(path, image) -> None:
    """Write an (H, W, 3) uint8 picture as PNG (atomically: all of it or nothing)."""
    buffer = io.BytesIO()
    _to_pil(image).save(buffer, format="PNG")
    atomic_write(path, buffer.getvalue())


def save_gif(path, frames, fps: float = 12.0) -> None:
    """Write pictures as an animated GIF that loops forever.

    Each frame gets its own 256-colour palette. GIF stores durations in hundredths of
    a second, so fps above 50 is not honoured by most viewers. Pillow merges
    consecutive identical frames into one longer frame.
    """
    pictures = [_to_pil(frame) for frame in frames]
    if not pictures:
        raise ValueError("frames is empty; at least one frame is needed")
    rate = float(fps)
    if not np.isfinite(rate) or rate <= 0:
        raise ValueError(f"fps must be finite and > 0, got {fps!r}")

    paletted = [p.convert("P", palette=Image.Palette.ADAPTIVE, colors=256) for p in pictures]
    buffer = io.BytesIO()
    paletted[0].save(buffer, format="GIF", save_all=True, append_images=paletted[1:],
                     duration=int(round(1000.0 / rate)), loop=0, optimize=False)
    atomic_write(path, buffer.getvalue())

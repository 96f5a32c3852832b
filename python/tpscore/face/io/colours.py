"""A mesh's colours: the texture image an OBJ's material names, or the vertex colours
or texture trimesh reads (:func:`read_mesh_colours`, :class:`MeshColours`)."""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..._files import MAX_TEXT_FILE_BYTES, check_readable
from ..image import as_colour_image
from ._common import _read_text
from .images import read_image
from .mesh import read_mesh
from .obj import _read_obj


class ColourWarning(UserWarning):
    """A mesh's colour source cannot be used (a missing material or texture file, a
    material without an image, an unreadable image): the scan is read without colour."""


@dataclass
class MeshColours:
    """A mesh with the colours it carries, as :func:`read_mesh_colours` reads it.

    Attributes
    ----------
    vertices : (n, 3) float64, mm
    faces : (m, 3) int64
    image : (h, w, 3) uint8 or None
        The texture image.
    corner_uv : (m, 3, 2) float64 or None
        Each triangle corner's place in ``image`` in tpscore's convention (u to the
        right, v DOWN, as a ``.bnt`` holds it); a file's v = 0 at the image's bottom is
        flipped on reading.
    vertex_colors : (n, 3) uint8 or None
        Colours stored per vertex (PLY, GLB, OBJ ``v x y z r g b``).
    """

    vertices: np.ndarray
    faces: np.ndarray
    image: np.ndarray | None = None
    corner_uv: np.ndarray | None = None
    vertex_colors: np.ndarray | None = None


def _mtl_texture(mtl_path: Path, material: str | None) -> str | None:
    """The diffuse map (``map_Kd``) of `material` in a material library (the first one
    when `material` is None or not found)."""
    current, maps = None, {}
    for line in _read_text(mtl_path, MAX_TEXT_FILE_BYTES, "a material file"):
        words = line.split()
        if not words:
            continue
        if words[0] == "newmtl" and len(words) > 1:
            current = words[1]
        elif words[0].lower() == "map_kd" and len(words) > 1:
            # options (-s 1 1 1, ...) come before the file name, the last word
            maps.setdefault(current, words[-1])
    if material in maps:
        return maps[material]
    return next(iter(maps.values()), None)


def _texture_of_obj(path: Path, mtllib: str | None, material: str | None) -> np.ndarray | None:
    """The texture image an OBJ's material names, or None with a :class:`ColourWarning`."""
    where = repr(str(path))
    if mtllib is None:
        warnings.warn(f"{where} has texture coordinates but names no material library (mtllib): "
                      "read without colour", ColourWarning, stacklevel=4)
        return None
    mtl_path = path.parent / mtllib
    try:
        texture = _mtl_texture(check_readable(mtl_path, "material file"), material)
    except ValueError as exc:
        warnings.warn(f"{where}: its material library cannot be read ({exc}): read without colour",
                      ColourWarning, stacklevel=4)
        return None
    if texture is None:
        warnings.warn(f"{where}: its material library {str(mtl_path)!r} names no texture image (map_Kd): "
                      "read without colour", ColourWarning, stacklevel=4)
        return None
    try:
        return read_image(mtl_path.parent / texture)
    except ValueError as exc:
        warnings.warn(f"{where}: its texture image cannot be used ({exc}): read without colour",
                      ColourWarning, stacklevel=4)
        return None


def read_mesh_colours(path) -> MeshColours:
    """Read a mesh with its colours: an OBJ with its material library and texture image
    (:func:`write_textured_obj`'s output among them) or its vertex colours, a PLY, GLB or
    any other format trimesh reads with its vertex colours or texture.

    The vertices and faces are those :func:`read_mesh` reads. A colour source that
    cannot be used (a missing material or texture file, a material without an image,
    an unreadable image) gives a :class:`ColourWarning` and a mesh without colour.

    Raises
    ------
    ValueError
        As :func:`read_mesh`: a missing or unreadable mesh file.
    """
    path = check_readable(path)
    if path.suffix.lower() == ".obj":
        vertices, faces, extras = _read_obj(path, extras=True)
        result = MeshColours(vertices, faces)
        if extras["corner_uv"] is not None:
            image = _texture_of_obj(path, extras["mtllib"], extras["material"])
            if image is not None:
                flipped = extras["corner_uv"].copy()
                flipped[..., 1] = 1.0 - flipped[..., 1]
                result.image, result.corner_uv = image, flipped
        if result.image is None and extras["colors"] is not None:
            colors = extras["colors"]
            # OBJ colours are floats in [0, 1]; some writers store 0-255
            scale = 255.0 if colors.max() <= 1.0 else 1.0
            result.vertex_colors = np.clip(np.round(colors * scale), 0, 255).astype(np.uint8)
        return result
    vertices, faces = read_mesh(path)
    import trimesh

    result = MeshColours(vertices, faces)
    try:
        loaded = trimesh.load(str(path), process=False, fix_texture=False)
        if isinstance(loaded, trimesh.Scene):
            loaded = loaded.to_geometry() if hasattr(loaded, "to_geometry") else loaded.dump(concatenate=True)
        visual = getattr(loaded, "visual", None)
        kind = getattr(visual, "kind", None)
    except Exception:  # read_mesh read it; the colours are a bonus
        return result
    if len(getattr(loaded, "vertices", ())) != len(vertices):
        return result
    try:
        return _trimesh_colours(path, result, visual, kind)
    except Exception as exc:  # a visual trimesh built from a damaged file
        warnings.warn(f"{str(path)!r}: its colours cannot be read ({type(exc).__name__}: {exc}): read without "
                      "colour", ColourWarning, stacklevel=2)
        return MeshColours(vertices, faces)


def _trimesh_colours(path, result: MeshColours, visual, kind) -> MeshColours:
    """The vertex colours or the texture of a mesh trimesh read."""
    vertices, faces = result.vertices, result.faces
    if kind == "vertex":
        colors = np.asarray(visual.vertex_colors)
        if colors.shape[:1] == (len(vertices),) and colors.shape[1] >= 3:
            result.vertex_colors = np.ascontiguousarray(colors[:, :3], dtype=np.uint8)
    elif kind == "texture":
        uv = getattr(visual, "uv", None)
        material = getattr(visual, "material", None)
        picture = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        if uv is None or picture is None or len(faces) == 0:
            warnings.warn(f"{str(path)!r} has a texture but no image or texture coordinates tpscore can use: "
                          "read without colour", ColourWarning, stacklevel=3)
            return result
        try:
            image = as_colour_image(np.asarray(picture.convert("RGB"), dtype=np.uint8))
        except Exception as exc:
            warnings.warn(f"{str(path)!r}: its texture image cannot be used ({exc}): read without colour",
                          ColourWarning, stacklevel=3)
            return result
        corner_uv = np.asarray(uv, dtype=np.float64)[faces].copy()
        corner_uv[..., 1] = 1.0 - corner_uv[..., 1]
        if np.isfinite(corner_uv).all():
            result.image, result.corner_uv = image, corner_uv
    return result

"""Wavefront OBJ: the parser that keeps the file's vertex order, the writer, and an OBJ
textured by an image with its MTL and PNG (:func:`write_textured_obj`)."""
from __future__ import annotations

import io as _stdio
from pathlib import Path

import numpy as np

from ..._files import atomic_write
from ..._validation import as_faces, as_points
from ..image import as_colour_image
from ._common import MAX_MESH_FILE_BYTES, _read_text
from .images import write_png


def _read_obj(path, *, extras: bool = False):
    """Vertices and triangles of an OBJ file, in file order (polygons split as fans).

    With ``extras``, also the colour information: a dict with ``corner_uv`` ((m, 3, 2)
    texture coordinates of each triangle's corners as the file stores them, v up; None
    when a face has none), ``colors`` ((n, 3) floats of ``v x y z r g b`` lines, None
    unless every vertex has them), ``mtllib`` (the first material library named) and
    ``material`` (the first material used)."""
    where = repr(str(path))
    vertices: list[list[float]] = []
    colors: list[list[float]] = []
    texcoords: list[list[float]] = []
    faces: list[tuple[int, int, int]] = []
    face_texcoords: list[tuple[int, int, int]] = []
    every_face_textured = True
    mtllib = material = None
    for number, line in enumerate(_read_text(path, MAX_MESH_FILE_BYTES, "a mesh file"), start=1):
        words = line.split()
        if not words:
            continue
        try:
            if words[0] == "v":
                vertices.append([float(w) for w in words[1:4]])
                if len(vertices[-1]) != 3:
                    raise ValueError("a vertex needs x y z")
                if extras and len(words) >= 7:
                    colors.append([float(w) for w in words[4:7]])
            elif words[0] == "vt" and extras:
                texcoords.append([float(w) for w in words[1:3]])
                if len(texcoords[-1]) != 2:
                    raise ValueError("a texture coordinate needs u v")
            elif words[0] == "mtllib" and extras and mtllib is None and len(words) > 1:
                mtllib = line.split(None, 1)[1].strip()
            elif words[0] == "usemtl" and extras and material is None and len(words) > 1:
                material = words[1]
            elif words[0] == "f":
                corners, corner_texcoords = [], []
                for word in words[1:]:
                    parts = word.split("/")
                    index = int(parts[0])
                    # OBJ indices are 1-based; negative ones count back from the last vertex.
                    index = index - 1 if index > 0 else len(vertices) + index
                    if not 0 <= index < len(vertices):
                        raise ValueError(f"face refers to vertex {word!r}, which is not defined")
                    corners.append(index)
                    if extras and len(parts) > 1 and parts[1]:
                        texcoord = int(parts[1])
                        texcoord = texcoord - 1 if texcoord > 0 else len(texcoords) + texcoord
                        if not 0 <= texcoord < len(texcoords):
                            raise ValueError(f"face refers to texture coordinate {word!r}, which is not defined")
                        corner_texcoords.append(texcoord)
                if len(corners) < 3:
                    raise ValueError("a face needs at least 3 vertices")
                faces.extend((corners[0], corners[k], corners[k + 1]) for k in range(1, len(corners) - 1))
                if extras:
                    if len(corner_texcoords) == len(corners):
                        face_texcoords.extend((corner_texcoords[0], corner_texcoords[k], corner_texcoords[k + 1])
                                              for k in range(1, len(corners) - 1))
                    else:
                        every_face_textured = False
        except ValueError as exc:
            raise ValueError(f"{where}, line {number}: {exc}") from None
    if not vertices:
        raise ValueError(f"{where}: the file holds no vertices")
    vertices_array = np.array(vertices, dtype=np.float64)
    if not np.isfinite(vertices_array).all():
        raise ValueError(f"{where}: the file has NaN or infinite vertex coordinates")
    faces_array = np.array(faces, dtype=np.int64).reshape(-1, 3)
    if not extras:
        return vertices_array, faces_array
    corner_uv = None
    if every_face_textured and len(faces) and len(face_texcoords) == len(faces):
        corner_uv = np.array(texcoords, dtype=np.float64)[np.array(face_texcoords, dtype=np.int64)]
        if not np.isfinite(corner_uv).all():
            corner_uv = None
    color_array = None
    if len(colors) == len(vertices):
        color_array = np.array(colors, dtype=np.float64)
        if not np.isfinite(color_array).all():
            color_array = None
    return vertices_array, faces_array, {"corner_uv": corner_uv, "colors": color_array,
                                         "mtllib": mtllib, "material": material}


def _obj_bytes(vertices, faces, uv, colors, header: tuple[str, ...] = ()) -> bytes:
    out = _stdio.StringIO()
    out.write("# written by tpscore; units mm\n")
    for line in header:
        out.write(line + "\n")
    # %.17g round-trips float64 exactly; np.savetxt formats the whole block in C.
    if colors is None:
        np.savetxt(out, vertices, fmt="v %.17g %.17g %.17g")
    else:
        block = np.concatenate([vertices, colors[:, :3] / 255.0], axis=1)
        np.savetxt(out, block, fmt="v %.17g %.17g %.17g %.6g %.6g %.6g")
    if uv is not None:
        np.savetxt(out, uv, fmt="vt %.17g %.17g")
    if len(faces):
        one_based = faces + 1
        if uv is not None:
            np.savetxt(out, np.repeat(one_based, 2, axis=1), fmt="f %d/%d %d/%d %d/%d")
        else:
            np.savetxt(out, one_based, fmt="f %d %d %d")
    return out.getvalue().encode("ascii")


def write_textured_obj(path, vertices, faces, uv, image, *, material: str = "skin") -> tuple[Path, Path, Path]:
    """Write a mesh textured by an image: ``NAME.obj``, ``NAME.mtl`` and ``NAME_texture.png``.

    MeshLab, Blender, trimesh and most viewers show the mesh in the image's colours. The
    image and the material are written first, the OBJ last (each atomically), so an OBJ
    on disk always finds its material and image beside it.

    Parameters
    ----------
    path : str or PathLike
        The ``.obj`` file; the ``.mtl`` and the ``_texture.png`` take its stem, in its
        folder (the image's name differs from the stem so that a picture named like the
        mesh, ``result.obj`` beside ``result.png``, does not overwrite the texture).
    vertices : (n, 3) array-like, mm, finite
    faces : (m, 3) integer array-like
    uv : (n, 2) array-like
        Each vertex's place in the image in tpscore's convention (u to the right, v
        DOWN, in [0, 1], as :attr:`FaceGrid.uv <tpscore.face.grid.FaceGrid.uv>` and a
        ``.bnt`` hold it). The OBJ stores ``1 - v``, since OBJ viewers put v = 0 at the
        bottom of the image.
    image : (h, w, 3) uint8
        The texture, for example :attr:`FaceGrid.image <tpscore.face.grid.FaceGrid.image>`.
    material : str
        The material's name (letters, digits, ``_`` and ``-``).

    Returns
    -------
    (obj_path, mtl_path, png_path)
    """
    path = Path(path)
    if path.suffix.lower() != ".obj":
        raise ValueError(f"{str(path)!r}: write_textured_obj writes an .obj (with .mtl and .png beside it)")
    if not isinstance(material, str) or not material or not all(c.isalnum() or c in "_-" for c in material):
        raise ValueError(f"material must be a name of letters, digits, _ and -, got {material!r}")
    vertices = as_points(vertices, "vertices")
    faces = as_faces(np.asarray(faces).reshape(-1, 3) if np.size(faces) == 0 else faces, len(vertices))
    uv = as_points(uv, "uv", dim=2)
    if len(uv) != len(vertices):
        raise ValueError(f"uv must have shape ({len(vertices)}, 2), got {uv.shape}")
    picture = as_colour_image(image, "image")
    mtl_path, png_path = path.with_suffix(".mtl"), path.with_name(f"{path.stem}_texture.png")
    write_png(png_path, picture)
    atomic_write(mtl_path, (
        "# written by tpscore\n"
        f"newmtl {material}\n"
        "Ka 1 1 1\nKd 1 1 1\nKs 0 0 0\nNs 1\nd 1\nillum 1\n"
        f"map_Kd {png_path.name}\n").encode("utf-8"))
    flipped = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])
    atomic_write(path, _obj_bytes(vertices, faces, flipped, None,
                                   (f"mtllib {mtl_path.name}", f"usemtl {material}")))
    return path, mtl_path, png_path

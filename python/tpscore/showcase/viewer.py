"""A result page: one self-contained HTML file that shows an animated face in a browser.

The page holds the target's neutral face, the displacement field of the transfer, the
normals of both ends of the motion, the u,v map and the target's photograph, as base64
inside the file, and draws them with a small WebGL viewer (``tpscore/data/viewer/``: the page,
its script and its two shaders, all tpscore's own). The animation is linear in the
magnitude, so the browser holds the neutral face and the field and moves every vertex
on the GPU as the slider moves; the face turns with the mouse and zooms with the wheel.
Nothing is fetched from the network: the file works offline and can be mailed.
"""
from __future__ import annotations

import base64
import html
import io
import json
from importlib import resources
from pathlib import Path
from typing import Mapping

import numpy as np
from PIL import Image

from .._validation import as_faces, as_points
from .._version import __version__
from ..face.image import as_colour_image
from .._files import atomic_write
from ..mesh import vertex_normals

__all__ = ["page_html", "write_html", "write_result_html", "rig_page_html", "write_rig_html"]

# The page's typed arrays are read straight out of one buffer, and a Float32Array must
# start at a multiple of 4 bytes.
_ALIGNMENT = 4


def _asset(name: str) -> str:
    return resources.files("tpscore").joinpath("data", "viewer", name).read_text(encoding="utf-8")


def _pack(arrays: dict) -> tuple[str, dict]:
    """One base64 buffer holding every array, and where each lies in it."""
    blob = bytearray()
    layout = {}
    for name, array in arrays.items():
        blob.extend(b"\0" * (-len(blob) % _ALIGNMENT))
        data = np.ascontiguousarray(array)
        layout[name] = [str(data.dtype), len(blob), int(data.size)]
        blob.extend(data.astype(data.dtype.newbyteorder("<"), copy=False).tobytes())
    return base64.b64encode(bytes(blob)).decode("ascii"), layout


def _png_data_uri(image: np.ndarray) -> str:
    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image), "RGB").save(buffer, format="PNG", optimize=True)
    return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")


def _unit_normals_int8(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    # 8 bits a component are a third of a degree at worst: invisible in shading
    return np.round(vertex_normals(vertices, faces) * 127.0).astype(np.int8)


def page_html(neutral, field, faces, *, uv=None, image=None, title: str = "tpscore result",
              subtitle: str = "", magnitude: float = 1.0, max_magnitude: float = 1.0,
              slider_label: str = "magnitude") -> str:
    """The HTML text of a result page.

    Parameters
    ----------
    neutral : (n, 3) array_like, mm
        The face at magnitude 0 (finite).
    field : (n, 3) array_like, mm
        Each vertex's displacement at magnitude 1: the page draws ``neutral + m * field``.
    faces : (m, 3) array_like of int
    uv : (n, 2) array_like, optional
        Each vertex's place in `image` (u right, v down, in [0, 1]).
    image : (h, w, 3) uint8, optional
        The face's photograph; without it the face is clay-coloured.
    title, subtitle : str
        Shown above the face (as text: HTML in them is escaped).
    magnitude : float
        Where the slider starts.
    max_magnitude : float
        The slider's end (> 0).
    slider_label : str
        The slider's name.
    """
    neutral = as_points(neutral, "neutral")
    field = as_points(field, "field")
    if field.shape != neutral.shape:
        raise ValueError(f"field must have the shape of neutral {neutral.shape}, got {field.shape}")
    faces = as_faces(faces, len(neutral), "faces")
    if len(faces) == 0:
        raise ValueError("faces is empty: a page needs triangles to draw")
    if (uv is None) != (image is None):
        raise ValueError("uv and image go together: give both or neither")
    max_magnitude = float(max_magnitude)
    magnitude = float(magnitude)
    if not (np.isfinite(max_magnitude) and max_magnitude > 0):
        raise ValueError(f"max_magnitude must be finite and > 0, got {max_magnitude!r}")
    if not (np.isfinite(magnitude) and 0 <= magnitude <= max_magnitude):
        raise ValueError(f"magnitude must lie in [0, max_magnitude = {max_magnitude:g}], got {magnitude!r}")

    moved = neutral + field
    arrays = {
        "neutral": neutral.astype(np.float32),
        "field": field.astype(np.float32),
        "normal_neutral": _unit_normals_int8(neutral, faces),
        "normal_moved": _unit_normals_int8(moved, faces),
    }
    return _page(arrays, neutral, [moved], faces, uv, image, title=title, subtitle=subtitle,
                 slider_label=slider_label, magnitude=magnitude, max_magnitude=max_magnitude)


def rig_page_html(neutral, targets, faces, *, uv=None, image=None, title: str = "tpscore rig",
                  subtitle: str = "") -> str:
    """The HTML text of a rig's page: the neutral face with a slider per morph target
    (the face drawn is the neutral plus each target's displacement times its slider)
    and one that scales them all.

    Parameters
    ----------
    neutral : (n, 3) array_like, mm
    targets : sequence of (name, (n, 3) displacement in mm)
    faces, uv, image, title, subtitle
        As for :func:`page_html`.
    """
    neutral = as_points(neutral, "neutral")
    faces = as_faces(faces, len(neutral), "faces")
    targets = list(targets)
    if not targets:
        raise ValueError("targets is empty: a rig's page needs at least one morph target")
    arrays = {"neutral": neutral.astype(np.float32), "normal_neutral": _unit_normals_int8(neutral, faces)}
    names, moved = [], []
    for k, entry in enumerate(targets):
        if not (isinstance(entry, tuple) and len(entry) == 2 and isinstance(entry[0], str)):
            raise ValueError(f"targets[{k}] must be a (name, displacement) pair, got {type(entry).__name__}")
        name, displacement = entry
        displacement = as_points(displacement, f"targets[{k}] ({name})")
        if displacement.shape != neutral.shape:
            raise ValueError(f"targets[{k}] ({name}) must have the shape of neutral {neutral.shape}, "
                             f"got {displacement.shape}")
        names.append(name)
        moved.append(neutral + displacement)
        arrays[f"field_{k}"] = displacement.astype(np.float32)
        arrays[f"normal_{k}"] = _unit_normals_int8(moved[-1], faces)
    return _page(arrays, neutral, moved, faces, uv, image, title=title, subtitle=subtitle,
                 slider_label="all targets", magnitude=1.0, max_magnitude=1.0, targets=names)


def _page(arrays: dict, neutral, moved: list, faces, uv, image, *, title, subtitle, slider_label, magnitude,
          max_magnitude, targets=None) -> str:
    """The page of checked arrays: the texture, the indices, the view's centre and
    radius (the neutral and every moved face inside it) and the template filled in."""
    if (uv is None) != (image is None):
        raise ValueError("uv and image go together: give both or neither")
    if len(faces) == 0:
        raise ValueError("faces is empty: a page needs triangles to draw")
    centre = (neutral.min(axis=0) + neutral.max(axis=0)) / 2
    radius = float(max([np.linalg.norm(neutral - centre, axis=1).max(), 1.0]
                       + [np.linalg.norm(face - centre, axis=1).max() for face in moved]))
    texture = None
    if image is not None:
        uv = as_points(uv, "uv", dim=2)
        if len(uv) != len(neutral):
            raise ValueError(f"uv must have shape ({len(neutral)}, 2), got {uv.shape}")
        arrays["uv"] = np.round(np.clip(uv, 0.0, 1.0) * 65535.0).astype(np.uint16)
        texture = _png_data_uri(as_colour_image(image, "image"))
    else:
        arrays["uv"] = np.zeros((len(neutral), 2), dtype=np.uint16)
    # 16-bit indices work on every WebGL; larger meshes need 32
    arrays["indices"] = faces.astype(np.uint16 if len(neutral) <= 65536 else np.uint32)
    buffer, layout = _pack(arrays)
    data = {"buffer": buffer, "layout": layout, "texture": texture,
            "centre": [float(v) for v in centre], "radius": radius}
    if targets is not None:
        data["targets"] = list(targets)
    # "</" would end the <script> element that holds the JSON
    data_text = json.dumps(data).replace("</", "<\\/")

    replacements = {
        "{{VERSION}}": html.escape(__version__),
        "{{TITLE}}": html.escape(title),
        "{{SUBTITLE}}": html.escape(subtitle),
        "{{SLIDER_LABEL}}": html.escape(slider_label),
        "{{MAX}}": f"{max_magnitude:g}",
        "{{START}}": f"{magnitude:.2f}",
        "{{VERTEX_SHADER}}": _asset("face.vert"),
        "{{FRAGMENT_SHADER}}": _asset("face.frag"),
        "{{SCRIPT}}": _asset("viewer.js"),
        "{{DATA}}": data_text,
    }
    page = _asset("page.html")
    # one pass, so nothing substituted is ever read as a placeholder
    pieces = page.split("{{")
    out = [pieces[0]]
    for piece in pieces[1:]:
        key, _, rest = piece.partition("}}")
        out.append(replacements["{{" + key + "}}"] + rest)
    return "".join(out)


def write_html(path, neutral, field, faces, **kwargs) -> None:
    """Write :func:`page_html` to `path` (atomically); keyword arguments as there."""
    if Path(path).suffix.lower() not in (".html", ".htm"):
        raise ValueError(f"{str(path)!r}: a result page is an .html file")
    atomic_write(path, page_html(neutral, field, faces, **kwargs).encode("utf-8"))


def write_result_html(path, result, *, title: str | None = None) -> None:
    """Write the page of a :class:`~tpscore.expression.TransferResult`: the target in its
    own scan frame and colours, with a slider for the magnitude.

    For one magnitude m, the slider runs from 0 to max(1, m) and starts at m; for a
    weight per AU, it scales all the weights together from 0 to 1.
    """
    grid = result.target.grid
    mesh = result.mesh()  # an opened mouth is an opening in the mesh
    index = mesh.grid_index
    neutral = result.neutral.reshape(-1, 3)[index]
    labels = "+".join(result.animation.labels)
    if isinstance(result.magnitude, Mapping):
        field = result.field_in_scan().reshape(-1, 3)[index]
        start, end, label = 1.0, 1.0, "weight"
        subtitle = "the weights " + ", ".join(f"{k} {float(v):g}" for k, v in result.magnitude.items())
    else:
        field = (result.animation.frame_in_scan(1.0) - result.neutral).reshape(-1, 3)[index]
        start = float(result.magnitude)
        end = max(1.0, start)
        label = "magnitude"
        subtitle = f"transferred at magnitude {start:g}"
    page_title = title or f"tpscore: {labels} on the target"
    textured = grid.image is not None
    write_html(path, neutral, field, mesh.faces, uv=mesh.uv if textured else None,
               image=grid.image if textured else None, title=page_title,
               subtitle=subtitle + "; the slider moves the face on the GPU", magnitude=min(max(start, 0.0), end),
               max_magnitude=end, slider_label=label)


def write_rig_html(path, neutral, targets, faces, **kwargs) -> None:
    """Write :func:`rig_page_html` to `path` (atomically); keyword arguments as there."""
    if Path(path).suffix.lower() not in (".html", ".htm"):
        raise ValueError(f"{str(path)!r}: a rig's page is an .html file")
    atomic_write(path, rig_page_html(neutral, targets, faces, **kwargs).encode("utf-8"))

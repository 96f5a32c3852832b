"""The rig as glTF 2.0: one binary ``.glb`` (or a ``.gltf`` with its data inline) that
Blender, Maya, Unity, Unreal, three.js and most viewers open with the morph targets as
shape keys.

Written here with NumPy and JSON to the glTF 2.0 specification: one mesh, one
primitive of triangles over the target's valid grid vertices; POSITION in metres in
the target scan's frame (tpscore's frame is glTF's: +y up, the face toward +z, so only
the unit changes), NORMAL, TEXCOORD_0 and the target's photograph embedded as a PNG
base-colour texture; one morph target of POSITION (and NORMAL) displacements per rig
target, named in ``mesh.extras.targetNames``, every default weight 0; optionally one
animation per expression that takes its targets from 0 to 1 and back in a second.
"""
from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np

from .._files import atomic_write
from .._validation import as_path
from .._version import __version__
from ..face.io import png_bytes
from ..mesh import vertex_normals
from .build import Rig

__all__ = ["write_gltf", "gltf_document", "METRES_PER_MM", "ANIMATION_SECONDS"]

#: glTF's unit is the metre, tpscore's the millimetre.
METRES_PER_MM = 1e-3
#: An animation's length: neutral at 0, the expression at half of it, neutral again.
ANIMATION_SECONDS = 1.0

_FLOAT, _UNSIGNED_INT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_TRIANGLES = 4
_LINEAR, _LINEAR_MIPMAP_LINEAR, _CLAMP_TO_EDGE = 9729, 9987, 33071
_TYPES = {1: "SCALAR", 2: "VEC2", 3: "VEC3"}
_GLB_MAGIC, _GLB_VERSION = 0x46546C67, 2
_JSON_CHUNK, _BIN_CHUNK = 0x4E4F534A, 0x004E4942
# The colour of a face without a photograph: clay, as tpscore's pictures draw it.
_CLAY = [0.78, 0.70, 0.62, 1.0]


class _Buffer:
    """The one binary buffer and its views and accessors, each view starting on a
    4-byte boundary (the specification's alignment for every component type here)."""

    def __init__(self):
        self.data = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        self.data += b"\0" * (-len(self.data) % 4)
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.data += data
        self.views.append(view)
        return len(self.views) - 1

    def accessor(self, array: np.ndarray, target: int | None = None) -> int:
        """An accessor of a float32 (count, k) or uint32 (count,) array, tightly packed,
        with its min and max (which POSITION and animation inputs must have; the
        others carry them too, for readers that check bounds)."""
        array = np.ascontiguousarray(array)
        columns = 1 if array.ndim == 1 else array.shape[1]
        component = _FLOAT if array.dtype == np.float32 else _UNSIGNED_INT
        rows = array.reshape(len(array), columns)
        accessor = {"bufferView": self.view(array.tobytes(), target), "componentType": component,
                    "count": len(array), "type": _TYPES[columns]}
        if len(array):
            # float32 values widened to Python floats are exact, so the bounds match the data
            cast = float if component == _FLOAT else int
            accessor["min"] = [cast(v) for v in rows.min(axis=0)]
            accessor["max"] = [cast(v) for v in rows.max(axis=0)]
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def _normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit vertex normals; a vertex in no triangle (the rig's mesh drops a few between
    the lips) faces +z, as the face does, since glTF wants every normal of unit length."""
    normals = vertex_normals(vertices, triangles)
    normals[np.linalg.norm(normals, axis=1) == 0] = (0.0, 0.0, 1.0)
    return normals


def gltf_document(rig: Rig, *, animations: bool = False, normals: bool = True) -> tuple[dict, bytes]:
    """The glTF JSON document of a rig and its binary buffer (see the module's text)."""
    if not isinstance(rig, Rig):
        raise ValueError(f"rig must be a Rig (made by tpscore.rig), got {type(rig).__name__}")
    buffer = _Buffer()
    positions = (rig.vertices * METRES_PER_MM).astype(np.float32)
    attributes = {"POSITION": buffer.accessor(positions, _ARRAY_BUFFER)}
    neutral_normals = None
    if normals:
        neutral_normals = _normals(rig.vertices, rig.triangles)
        attributes["NORMAL"] = buffer.accessor(neutral_normals.astype(np.float32), _ARRAY_BUFFER)
    attributes["TEXCOORD_0"] = buffer.accessor(rig.uv.astype(np.float32), _ARRAY_BUFFER)  # both v down
    indices = buffer.accessor(rig.triangles.astype(np.uint32).reshape(-1), _ELEMENT_ARRAY_BUFFER)
    targets = []
    for target in rig.targets:
        morph = {"POSITION": buffer.accessor((target.displacement * METRES_PER_MM).astype(np.float32),
                                             _ARRAY_BUFFER)}
        if normals:
            # the normals' change too, so that shading follows the moved skin
            moved = _normals(rig.vertices + target.displacement, rig.triangles)
            morph["NORMAL"] = buffer.accessor((moved - neutral_normals).astype(np.float32), _ARRAY_BUFFER)
        targets.append(morph)
    material = {"name": "skin", "doubleSided": True,  # an open sheet of skin, seen from behind too
                "pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 0.8}}
    document = {"asset": {"version": "2.0", "generator": f"tpscore {__version__}"}}
    if rig.image is not None:
        image = buffer.view(png_bytes(rig.image))
        document.update(images=[{"bufferView": image, "mimeType": "image/png", "name": "target photograph"}],
                        samplers=[{"magFilter": _LINEAR, "minFilter": _LINEAR_MIPMAP_LINEAR,
                                   "wrapS": _CLAMP_TO_EDGE, "wrapT": _CLAMP_TO_EDGE}],
                        textures=[{"sampler": 0, "source": 0}])
        material["pbrMetallicRoughness"]["baseColorTexture"] = {"index": 0, "texCoord": 0}
    else:
        material["pbrMetallicRoughness"]["baseColorFactor"] = _CLAY
    primitive = {"attributes": attributes, "indices": indices, "material": 0, "mode": _TRIANGLES}
    if targets:
        primitive["targets"] = targets
    mesh = {"name": "face", "primitives": [primitive], "weights": [0.0] * len(targets),
            "extras": {"targetNames": rig.target_names}}
    document.update(scene=0, scenes=[{"name": "rig", "nodes": [0]}], nodes=[{"name": "face", "mesh": 0}],
                    meshes=[mesh], materials=[material])
    if animations and targets:
        document["animations"] = _animations(rig, buffer)
    document.update(accessors=buffer.accessors, bufferViews=buffer.views)
    data = bytes(buffer.data + b"\0" * (-len(buffer.data) % 4))
    document["buffers"] = [{"byteLength": len(data)}]
    return document, data


def _animations(rig: Rig, buffer: _Buffer) -> list[dict]:
    """One animation per expression: its morph targets (both halves of a split one)
    from 0 to 1 and back to 0, linearly, the others held at 0."""
    times = np.array([0.0, 0.5, 1.0], dtype=np.float32) * ANIMATION_SECONDS
    keys = buffer.accessor(times)
    out = []
    for expression in rig.results:
        weights = np.zeros((len(times), len(rig.targets)), dtype=np.float32)
        weights[1] = [t.expression == expression for t in rig.targets]
        sampler = {"input": keys, "output": buffer.accessor(weights.reshape(-1)), "interpolation": "LINEAR"}
        out.append({"name": expression, "samplers": [sampler],
                    "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]})
    return out


def write_gltf(path, rig: Rig, *, animations: bool = False, normals: bool = True) -> Path:
    """Write a rig as glTF 2.0: ``.glb`` (binary, one file) or ``.gltf`` (JSON with the
    buffer and the texture inline as a data URI), atomically.

    Parameters
    ----------
    path : str or PathLike
    rig : Rig
    animations : bool
        Add one animation per expression (its targets 0 -> 1 -> 0 over
        :data:`ANIMATION_SECONDS`), for players that play a file's animations.
    normals : bool
        Write vertex normals and their change in each morph target (viewers otherwise
        compute flat or smooth normals of their own).

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    ValueError
        `path` does not end in ``.glb`` or ``.gltf``, or its folder does not exist;
        `rig` is not a Rig.
    """
    target = Path(as_path(path, "path"))
    suffix = target.suffix.lower()
    if suffix not in (".glb", ".gltf"):
        raise ValueError(f"path: {str(target)!r}: a glTF file ends in .glb (binary) or .gltf")
    document, data = gltf_document(rig, animations=animations, normals=normals)
    if suffix == ".gltf":
        document["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(data).decode()
        atomic_write(target, json.dumps(document, indent=1).encode("utf-8"), "path")
        return target
    text = json.dumps(document, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)  # the JSON chunk is padded with spaces, the binary one with zeros
    length = 12 + 8 + len(text) + 8 + len(data)
    atomic_write(target, b"".join([struct.pack("<III", _GLB_MAGIC, _GLB_VERSION, length),
                                   struct.pack("<II", len(text), _JSON_CHUNK), text,
                                   struct.pack("<II", len(data), _BIN_CHUNK), data]), "path")
    return target

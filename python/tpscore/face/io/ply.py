"""Binary little-endian PLY meshes, as :func:`~tpscore.face.io.write_mesh` writes them."""
from __future__ import annotations

import numpy as np


def _ply_bytes(vertices, faces, uv, colors) -> bytes:
    n, m = len(vertices), len(faces)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    header = ["ply", "format binary_little_endian 1.0", "comment written by tpscore; units mm",
              f"element vertex {n}", "property double x", "property double y", "property double z"]
    if uv is not None:
        fields += [("texture_u", "<f8"), ("texture_v", "<f8")]
        header += ["property double texture_u", "property double texture_v"]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")]
        header += ["property uchar red", "property uchar green", "property uchar blue", "property uchar alpha"]
    header += [f"element face {m}", "property list uchar int vertex_indices", "end_header"]
    table = np.empty(n, dtype=np.dtype(fields))
    table["x"], table["y"], table["z"] = vertices[:, 0], vertices[:, 1], vertices[:, 2]
    if uv is not None:
        table["texture_u"], table["texture_v"] = uv[:, 0], uv[:, 1]
    if colors is not None:
        for k, name in enumerate(("red", "green", "blue", "alpha")):
            table[name] = colors[:, k]
    face_table = np.empty(m, dtype=np.dtype([("count", "u1"), ("indices", "<i4", (3,))]))
    face_table["count"] = 3
    face_table["indices"] = faces
    return ("\n".join(header) + "\n").encode("ascii") + table.tobytes() + face_table.tobytes()

"""Reading and writing scans, landmarks and meshes, one module per format.

Formats:

- Bosphorus ``.bnt`` depth scans (:func:`read_bnt`, :func:`write_bnt`; :mod:`.bnt`);
- Bosphorus ``.lm3`` landmark files (:func:`read_lm3`, :func:`write_lm3`), and
  landmarks as ``.csv`` or ``.json`` (:func:`read_landmarks`, :func:`write_landmarks`;
  :mod:`.landmarks`);
- meshes and point clouds through trimesh (:func:`read_mesh`), OBJ / PLY meshes
  with a u,v map and vertex colours (:func:`write_mesh`; :mod:`.mesh`, :mod:`.obj`,
  :mod:`.ply`), a mesh's texture or vertex colours (:func:`read_mesh_colours`;
  :mod:`.colours`), and an OBJ textured by an image, with its MTL and PNG
  (:func:`write_textured_obj`; :mod:`.obj`);
- colour images (:func:`read_image`, :func:`write_png`; :mod:`.images`) and NumPy
  ``.npz`` archives (:func:`read_npz`, :func:`write_npz`; :mod:`.npz`).

Landmarks are always a (22, 3) float64 array in Bosphorus order (see
:mod:`tpscore.face.landmarks`) with NaN rows for the ones that are missing. Every reader
raises ValueError naming the file and what is wrong with it; every writer writes to
a temporary file beside the target and renames it, so nothing is left half-written.
Units are millimetres.
"""
from __future__ import annotations

from ._common import MAX_MESH_FILE_BYTES
from .bnt import DEFAULT_BNT_ZMIN, MAX_BNT_POINTS, BntScan, read_bnt, write_bnt
from .colours import ColourWarning, MeshColours, read_mesh_colours
from .images import MAX_IMAGE_PIXELS, png_bytes, read_image, write_png
from .landmarks import (IGNORED_LM3_NAMES, LANDMARK_SUFFIXES, MAX_LANDMARK_COORDINATE, landmark_file_beside,
                        read_landmarks, read_lm3, write_landmarks, write_lm3)
from .mesh import read_mesh, write_mesh
from .npz import MAX_NPZ_BYTES, read_npz, write_npz
from .obj import write_textured_obj

__all__ = [
    "BntScan",
    "read_npz",
    "write_npz",
    "read_bnt",
    "write_bnt",
    "read_lm3",
    "write_lm3",
    "read_landmarks",
    "landmark_file_beside",
    "write_landmarks",
    "read_mesh",
    "read_mesh_colours",
    "MeshColours",
    "ColourWarning",
    "write_mesh",
    "write_textured_obj",
    "png_bytes",
    "write_png",
    "read_image",
]

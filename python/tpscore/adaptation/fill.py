"""The fill after the ``"surface"`` levels: template vertices the scan never showed take
their displacement from their own rims, along the template mesh.

The whole displacement is filled, not only the refinement's offsets: level 0's field
over space carries the same fault (a nostril takes the upper lip's displacement). A
mesh fill does not reproduce a linear field on a curved surface, so an affine map is no
longer reproduced exactly at the unpaired vertices (about 0.3 mm for a 5 % shear; see
the tests). docs/adaptation.md has the measurements.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..mesh import cotan_laplacian

__all__ = ["fill_unseen", "fill_unseen_offsets"]


def fill_unseen(template_vertices, template_faces, deformed, anchors) -> np.ndarray:
    """The fit `deformed` with every vertex but the `anchors` (indices) given the harmonic
    fill of the anchors' displacements (:func:`fill_unseen_offsets`)."""
    anchored = np.zeros(len(template_vertices), dtype=bool)
    anchored[anchors] = True
    return template_vertices + fill_unseen_offsets(template_vertices, template_faces, deformed - template_vertices,
                                                   anchored)


def fill_unseen_offsets(template_vertices, template_faces, offsets, anchored) -> np.ndarray:
    """Offsets over the template with the unanchored vertices filled in along the mesh.

    The refinement levels know the scan only where the template was paired with it.
    Vertices the scanner could not see (inside the nostrils, between the lips, under
    the nose) are close in space to paired vertices of other parts of the face (the
    upper lip, the ala), so a field over 3D space hands them those parts' offsets.
    Along the mesh they are connected to their own rims instead: here their offsets
    are the harmonic interpolation of the anchored vertices' offsets, minimising
    ``d^T (-L) d`` (L: the cotangent Laplacian) with the anchored offsets fixed.

    Parameters
    ----------
    template_vertices : (n, 3) ndarray
        The undeformed template (mm).
    template_faces : (m, 3) int ndarray
    offsets : (n, 3) ndarray
        Current offsets (mm); kept at the anchored vertices.
    anchored : (n,) bool
        Vertices whose offsets the scan determined.

    Returns
    -------
    (n, 3) ndarray.
    """
    n = len(template_vertices)
    free = ~anchored
    used = np.zeros(n, dtype=bool)
    used[np.unique(template_faces)] = True
    free &= used
    if not free.any() or not anchored.any():
        return offsets
    operator = (-cotan_laplacian(template_vertices, template_faces)).tocsr()
    free_rows = np.flatnonzero(free)
    fixed_rows = np.flatnonzero(~free)
    a_ff = operator[free_rows][:, free_rows].tocsc()
    a_fx = operator[free_rows][:, fixed_rows]
    rhs = -(a_fx @ offsets[fixed_rows])
    # A tiny diagonal keeps islands of free vertices with no anchored neighbour solvable.
    a_ff = a_ff + 1e-9 * sp.identity(len(free_rows), format="csc")
    filled = offsets.copy()
    filled[free_rows] = spla.splu(a_ff).solve(np.asarray(rhs))
    return filled

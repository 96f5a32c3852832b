"""NumPy reference for the rigid point-to-plane ICP (tpscore.expression.alignment.align_rigid,
the compiled loop in rigid_icp.cpp): the same steps, one NumPy statement each."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["rigid_icp"]


def rigid_icp(fixed_surface, face_normals, sample, prior, start, iterations: int = 30,
              tukey_factor: float = 4.0, min_scale_mm: float = 0.3, tolerance_mm: float = 1e-3):
    """(matrix (4, 4), iterations run, inlier rms) of the ICP of sample (m, 3), with prior
    weights (m,), onto a :class:`tpscore.MeshSurface` whose triangles have unit normals
    face_normals, from the 4 x 4 start."""
    matrix = np.array(start, dtype=np.float64)
    done = 0
    inlier_rms = float("nan")
    for done in range(1, iterations + 1):
        moved = sample @ matrix[:3, :3].T + matrix[:3, 3]
        closest = fixed_surface.closest_point(moved)
        normals = face_normals[closest.triangles]
        # point-to-plane distance; a closest point on a triangle's edge (scan outline)
        # lies off the plane and is down-weighted by its large Euclidean distance too
        signed = np.einsum("ij,ij->i", moved - closest.points, normals)
        scale = max(1.4826 * float(np.median(closest.distances[prior > 0.5])
                                   if (prior > 0.5).any() else np.median(closest.distances)),
                    min_scale_mm)
        u = closest.distances / (tukey_factor * scale)
        weight = np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0) * prior
        if weight.sum() < 6:
            break
        # linearised point-to-plane step: rotation vector omega and translation t about
        # the sample's centroid (which keeps the 6 x 6 normal equations well scaled)
        centre = weight @ moved / weight.sum()
        jac = np.hstack([np.cross(moved - centre, normals), normals])
        normal_matrix = (jac * weight[:, None]).T @ jac + 1e-9 * np.eye(6)
        step = np.linalg.solve(normal_matrix, -(jac * weight[:, None]).T @ signed)
        rotation = Rotation.from_rotvec(step[:3]).as_matrix()
        update = np.eye(4)
        update[:3, :3] = rotation
        update[:3, 3] = centre + step[3:] - rotation @ centre
        matrix = update @ matrix
        inlier_rms = float(np.sqrt(np.average(signed ** 2, weights=weight)))
        motion = np.abs((moved - centre) @ (rotation - np.eye(3)).T + step[3:]).max()
        if motion < tolerance_mm:
            break
    return matrix, done, inlier_rms

"""New template-to-scan correspondences for each level of template adaptation.

The published levels take theirs from two sources, both paired by rays so that a pair
is only made where both surfaces are really there (a ray that misses, e.g. over a
hole, gives no pair, never a guess):

* the feature mesh: a triangulation of the corresponding feature points of the
  template and of the scan; each triangle is split at its barycentre, and a ray
  along the triangle's normal from that barycentre meets each surface at the new
  feature point (Kaehler et al.'s refinement). The points accumulate over levels;
* the template vertices of largest mean curvature (Meyer et al.) inside a bounding
  box of the face, paired with the scan by a ray along the deformed normal.

The default ``"surface"`` refinement pairs differently: every visible template vertex
with its closest scan point (:func:`closest_visible_pairs`), on centres spread evenly
over the template (:func:`tpscore.geometry.spread_vertices`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import Delaunay

from .._validation import as_faces, as_points
from ..mesh import boundary_vertices, face_normals, mean_curvature, vertex_normals
from ..spatial import MeshSurface

__all__ = [
    "FeatureMesh",
    "ScanTarget",
    "closest_visible_pairs",
    "curvature_features",
    "self_occluded",
    "triangulate_features",
]


class ScanTarget:
    """A scan surface prepared for the ray pairing of adaptation.

    Parameters
    ----------
    vertices : (n, 3) array_like
        Scan vertices (mm), in the frame the fit works in.
    faces : (m, 3) array_like of int
        Triangles; rays never pair with a triangle that touches the scan's open
        boundary (its outline and hole rims), where the surface is least reliable.
    """

    def __init__(self, vertices, faces):
        self.vertices = as_points(vertices, "scan vertices", allow_empty=False)
        self.faces = as_faces(faces, len(self.vertices), "scan faces")
        if len(self.faces) == 0:
            raise ValueError("scan has no triangles; adaptation needs a surface (a mesh or a grid)")
        self.surface = MeshSurface(self.vertices, self.faces)
        self.face_normals = face_normals(self.vertices, self.faces)
        self.vertex_normals = vertex_normals(self.vertices, self.faces)
        rim = boundary_vertices(self.faces, len(self.vertices))
        self.rim_vertices = rim
        self.rim_faces = rim[self.faces].any(axis=1)

    def cast(self, origins, directions, *, max_distance: float, min_cos: float = 0.5,
             view_direction=None, min_view_cos: float = 0.2):
        """Pair points with the scan by rays along `directions` (both ways).

        Parameters
        ----------
        origins, directions : (m, 3) ndarray
            Ray origins (mm) and directions (unit or not).
        max_distance : float
            Hits farther than this (mm) are ignored.
        min_cos : float
            The hit triangle's normal must be within arccos(min_cos) of the direction,
            so a ray does not pair a surface with one facing elsewhere (inner lips
            with the chin, a nostril with the upper lip).
        view_direction : (3,) array_like, optional
            Direction toward the scanner; points whose direction faces away from it
            by more than arccos(min_view_cos) cannot have been seen and get no pair.

        Returns
        -------
        hit : (m,) bool
        points : (m, 3) ndarray, NaN where not hit.
        """
        origins = np.ascontiguousarray(origins, dtype=np.float64)
        directions = np.ascontiguousarray(directions, dtype=np.float64)
        m = len(origins)
        if m == 0:
            return np.zeros(0, dtype=bool), np.zeros((0, 3))
        lengths = np.linalg.norm(directions, axis=1)
        usable = lengths > 0
        unit = np.zeros_like(directions)
        unit[usable] = directions[usable] / lengths[usable, None]
        if view_direction is not None:
            usable &= unit @ np.asarray(view_direction, dtype=np.float64) >= min_view_cos
        hit = np.zeros(m, dtype=bool)
        points = np.full((m, 3), np.nan)
        if not usable.any():
            return hit, points
        rays = self.surface.intersect_rays(origins[usable], unit[usable], max_distance=max_distance,
                                           both_directions=True)
        ok = rays.hit.copy()
        triangles = np.where(ok, rays.triangles, 0)
        ok &= ~self.rim_faces[triangles]
        ok &= np.einsum("ij,ij->i", self.face_normals[triangles], unit[usable]) >= min_cos
        where = np.flatnonzero(usable)
        hit[where] = ok
        points[where[ok]] = rays.points[ok]
        return hit, points

    def closest(self, points, normals, *, max_distance: float, min_cos: float = 0.5):
        """Pair points with their closest scan point (for point-to-plane fitting).

        Parameters
        ----------
        points, normals : (m, 3) ndarray
            Points (mm) and their unit normals.
        max_distance : float
            Partners farther than this (mm) are dropped.
        min_cos : float
            The scan normal there must be within arccos(min_cos) of the point's normal.

        Returns
        -------
        hit : (m,) bool
            False where the partner is too far, faces elsewhere or lies on a triangle
            touching the scan's open boundary (the point is beyond the scan or over a
            hole: its closest point is the rim, not its partner).
        points : (m, 3) ndarray
            The closest scan points (NaN where not hit).
        normals : (m, 3) ndarray
            The scan's unit normals there (interpolated vertex normals).
        """
        points = np.ascontiguousarray(points, dtype=np.float64)
        m = len(points)
        if m == 0:
            return np.zeros(0, dtype=bool), np.zeros((0, 3)), np.zeros((0, 3))
        closest = self.surface.closest_point(points)
        corner_normals = self.vertex_normals[self.faces[closest.triangles]]
        scan_normals = np.einsum("ij,ijk->ik", closest.barycentric, corner_normals)
        scan_normals /= np.maximum(np.linalg.norm(scan_normals, axis=1, keepdims=True), 1e-12)
        hit = closest.distances <= max_distance
        hit &= ~self.rim_faces[closest.triangles]
        hit &= np.einsum("ij,ij->i", scan_normals, normals) >= min_cos
        partners = np.where(hit[:, None], closest.points, np.nan)
        return hit, partners, scan_normals


def _plane_axes(view_direction) -> np.ndarray:
    """Two unit vectors spanning the plane orthogonal to the view direction."""
    view = np.asarray(view_direction, dtype=np.float64)
    view = view / np.linalg.norm(view)
    start = np.array([1.0, 0.0, 0.0]) if abs(view[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = start - (start @ view) * view
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(view, u)], axis=1)


def triangulate_features(points, view_direction=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Delaunay triangulation of feature points seen along `view_direction`.

    Parameters
    ----------
    points : (n, 3) array_like
        Feature points (mm), n >= 3, not all on one line in the view.
    view_direction : (3,) array_like
        The direction the face looks (the points are projected onto the plane
        orthogonal to it).

    Returns
    -------
    (m, 3) int64 triangles, counter-clockwise seen from the view direction.
    """
    points = as_points(points, "points")
    if len(points) < 3:
        raise ValueError(f"points: a feature mesh needs at least 3 points, got {len(points)}")
    flat = points @ _plane_axes(view_direction)
    try:
        triangles = Delaunay(flat).simplices.astype(np.int64)
    except Exception as exc:  # scipy raises QhullError for degenerate input
        raise ValueError(f"points cannot be triangulated (collinear in the view?): {exc}") from None
    a, b, c = (flat[triangles[:, k]] for k in range(3))
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    flip = cross < 0
    triangles[flip] = triangles[flip][:, [0, 2, 1]]
    return triangles


@dataclass
class FeatureMesh:
    """Corresponding feature points of template and scan, and their triangulation.

    Attributes
    ----------
    template_points : (n, 3) ndarray
        Feature points on the (undeformed) template, mm.
    scan_points : (n, 3) ndarray
        The corresponding scan points, mm, in the fit's frame.
    triangles : (m, 3) int64
        One triangulation shared by both point sets (made on the template side).
    view_direction : (3,) ndarray
        The direction the face looks, used for the triangulation.
    """

    template_points: np.ndarray
    scan_points: np.ndarray
    triangles: np.ndarray
    view_direction: np.ndarray

    @classmethod
    def build(cls, template_points, scan_points, view_direction=(0.0, 0.0, 1.0)) -> "FeatureMesh":
        template_points = as_points(template_points, "template_points")
        scan_points = as_points(scan_points, "scan_points")
        if template_points.shape != scan_points.shape:
            raise ValueError(f"scan_points must have shape {template_points.shape}, got {scan_points.shape}")
        view = np.asarray(view_direction, dtype=np.float64)
        return cls(template_points, scan_points, triangulate_features(template_points, view), view)

    def subdivide(self, template: MeshSurface, scan: ScanTarget, *, max_distance: float,
                  min_area: float = 1.0):
        """Split every triangle at its barycentre and project the new point onto both surfaces.

        Parameters
        ----------
        template : MeshSurface
            The undeformed template.
        scan : ScanTarget
            The scan, in the fit's frame.
        max_distance : float
            Longest ray (mm) on either side.
        min_area : float
            Triangles smaller than this (mm^2, on the template side) are not split:
            their barycentres would add pairs closer than the data can resolve.

        Returns
        -------
        FeatureMesh
            The refined mesh (old points first, then the new ones, re-triangulated).
        new_template_points, new_scan_points : (k, 3) ndarray
            The new pairs (only those where both rays hit).
        """
        # The edges' cross product gives both the area and the ray direction (rays are
        # normalised where they are cast). Unit normals from the mesh kernel differ from it
        # in the last bits, which once changed a single pair and, through the quadric CSRBF
        # levels, a benchmark subject's published-method result by 2 mm.
        t_cross = _edge_cross(self.template_points, self.triangles)
        big = 0.5 * np.linalg.norm(t_cross, axis=1) >= min_area
        if not big.any():
            return self, np.zeros((0, 3)), np.zeros((0, 3))
        triangles = self.triangles[big]
        t_centres = self.template_points[triangles].mean(axis=1)
        s_centres = self.scan_points[triangles].mean(axis=1)
        t_hits = template.intersect_rays(t_centres, t_cross[big], max_distance=max_distance, both_directions=True)
        s_hit, s_points = scan.cast(s_centres, _edge_cross(self.scan_points, triangles),
                                    max_distance=max_distance, min_cos=0.0)
        both = t_hits.hit & s_hit
        new_t, new_s = t_hits.points[both], s_points[both]
        if len(new_t) == 0:
            return self, new_t, new_s
        template_points = np.vstack([self.template_points, new_t])
        scan_points = np.vstack([self.scan_points, new_s])
        refined = FeatureMesh(template_points, scan_points,
                              triangulate_features(template_points, self.view_direction), self.view_direction)
        return refined, new_t, new_s


def _edge_cross(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(b - a) x (c - a) of each triangle: along its normal, twice its area long (mm^2)."""
    corners = points[triangles]
    return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def _greedy_spread(order: np.ndarray, points: np.ndarray, spacing: float) -> np.ndarray:
    """Walk `order` and keep each point farther than `spacing` from every kept one."""
    if spacing <= 0:
        return order
    cells: dict[tuple[int, int, int], list[int]] = {}
    kept = []
    keys = np.floor(points / spacing).astype(np.int64)
    limit = spacing * spacing
    for index in order:
        key = keys[index]
        close = False
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dz in (-1, 0, 1):
                    for other in cells.get((key[0] + dx, key[1] + dy, key[2] + dz), ()):
                        d = points[other] - points[index]
                        if d @ d < limit:
                            close = True
                            break
                    if close:
                        break
                if close:
                    break
            if close:
                break
        if not close:
            cells.setdefault((int(key[0]), int(key[1]), int(key[2])), []).append(int(index))
            kept.append(int(index))
    return np.asarray(kept, dtype=np.int64)


def curvature_features(vertices, faces, count: int, *, box=None, spacing: float = 0.0,
                       sign: str = "absolute") -> np.ndarray:
    """The vertices of largest mean curvature, spread out, inside a box.

    Parameters
    ----------
    vertices : (n, 3) array_like
        Mesh vertices (mm).
    faces : (m, 3) array_like of int
        Triangles, consistently oriented (outward normals).
    count : int
        How many vertices to return at most.
    box : ((3,), (3,)) array_like, optional
        Lower and upper corners (mm); only vertices inside are candidates.
    spacing : float
        No two returned vertices are closer than this (mm); 0 keeps the raw ranking.
    sign : {"absolute", "convex", "concave"}
        Rank by |H|, by H (bumps such as the nose tip) or by -H (folds).

    Returns
    -------
    (k,) int64 vertex indices, k <= count, largest curvature first. Boundary
    vertices (where the one-ring formula does not hold) are never chosen.
    """
    vertices = as_points(vertices, "vertices")
    faces = as_faces(faces, len(vertices), "faces")
    if sign not in ("absolute", "convex", "concave"):
        raise ValueError(f"sign must be 'absolute', 'convex' or 'concave', got {sign!r}")
    curvature = mean_curvature(vertices, faces).values
    score = {"absolute": np.abs(curvature), "convex": curvature, "concave": -curvature}[sign]
    candidate = np.isfinite(score)
    if box is not None:
        low, high = (np.asarray(c, dtype=np.float64) for c in box)
        candidate &= np.all((vertices >= low) & (vertices <= high), axis=1)
    indices = np.flatnonzero(candidate)
    order = indices[np.argsort(-score[indices], kind="stable")]
    # Only the best few times `count` can survive the spreading; the rest is not worth walking.
    order = order[: max(20 * int(count), 1)]
    return _greedy_spread(order, vertices, float(spacing))[: int(count)]


def self_occluded(vertices, faces, view_direction, *, offset: float = 0.3,
                  max_distance: float = 200.0) -> np.ndarray:
    """Vertices hidden from a viewer along `view_direction` by the mesh itself.

    A ray from each vertex (lifted by `offset` mm along the view so that it does not
    hit its own triangles) toward the viewer that meets the mesh means the vertex is
    behind another part of it: inside a nostril, between the lips, under the nose or
    the brow. A scanner looking along the same direction cannot have seen it, so such
    a vertex must not be paired with the scan (a pair would tie it to the surface in
    front of it).

    Parameters
    ----------
    vertices : (n, 3) array_like
        Mesh vertices (mm).
    faces : (m, 3) array_like of int
        Triangles.
    view_direction : (3,) array_like
        Direction from the mesh toward the viewer.
    offset : float
        Lift of the ray origins (mm).
    max_distance : float
        Longest ray (mm).

    Returns
    -------
    (n,) bool, True where hidden.
    """
    vertices = as_points(vertices, "vertices")
    faces = as_faces(faces, len(vertices), "faces")
    view = np.asarray(view_direction, dtype=np.float64).reshape(3)
    view = view / np.linalg.norm(view)
    surface = MeshSurface(vertices, faces)
    rays = surface.intersect_rays(vertices + offset * view, np.broadcast_to(view, vertices.shape),
                                  max_distance=max_distance)
    return rays.hit.copy()


def closest_visible_pairs(points, normals, faces, scan: ScanTarget, view_direction, *, max_distance: float):
    """Pair the vertices of a fitted template that the scanner could have seen with their
    closest scan points (point-to-plane pairs for the ``"surface"`` refinement and the
    snap).

    A vertex is visible when its normal is within about 78 degrees of the view direction
    (cos >= 0.2) and no part of the template hides it (:func:`self_occluded`).

    Parameters
    ----------
    points, normals : (n, 3) ndarray
        The fitted template's vertices (mm) and unit normals.
    faces : (m, 3) int ndarray
    scan : ScanTarget
    view_direction : (3,) ndarray or None
        Unit direction toward the scanner; None: every vertex counts as visible.
    max_distance : float
        Partners farther than this (mm) are dropped.

    Returns
    -------
    rows : (k,) int64
        The paired vertices.
    partners, partner_normals : (k, 3) ndarray
        Their closest scan points and the scan's unit normals there.
    """
    rows = np.arange(len(points))
    if view_direction is not None:
        rows = rows[(normals @ view_direction >= 0.2) & ~self_occluded(points, faces, view_direction)]
    hit, partners, partner_normals = scan.closest(points[rows], normals[rows], max_distance=max_distance)
    return rows[hit], partners[hit], partner_normals[hit]

"""Motion cut at the openings an expression opens or closes: the mouth that opens, the
eyes that close.

A smooth field over the face cannot move the upper lip up while the lower lip drops
with the jaw, nor slide an upper lid down across the eye while the lower lid stays:
it smears the two motions together across the opening. Where the source's expressive
scan shows an opening other than its neutral scan does (:func:`moved_openings`), the
motion is registered twice (:func:`register_cut`): once with the data on the upper
side of every moved opening (and everywhere outside their windows), once with the
lower side's; each side's field is then free of the other's motion, and the two agree
away from the openings, where both saw the same data. An eye's lids move over a few
millimetres, finer than the registration's lattice: each side of a moved eye gets a
local correction on a fine lattice (:func:`fit_local_correction`), pulled by where the
rims of the opening went (an upper lid that closes meets the lower lid).

A point takes the upper field above an opening's line, the lower one below it
(:func:`tpscore.face.openings.opening_sides`), in the frame of the face it lies on:
on the target, the target's own openings decide. docs/transfer.md has the method and
benchmarks/FIDELITY.md its measurements.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..face.landmarks import N_LANDMARKS
from ..face.openings import Opening, find_openings, grid_xy, opening_sides
from .._threads import side_by_side
from ..geometry import off_surface, robust_scale, tukey_weights
from ..lattice import BSplineLattice, LatticeSystem, symmetric_blocks
from ..mesh import face_normals
from ..spatial import MeshSurface

__all__ = ["CutMotion", "LocalCorrection", "moved_openings", "eye_windows", "register_cut", "fit_local_correction",
           "opening_pairs", "OPENED_MM", "OPENED_SHARE", "LOCAL_SPACING_MM", "LOCAL_REACH"]

#: An opening has moved when how far it is open (:meth:`Opening.open_mm`) in the
#: expressive scan differs from the neutral scan by more than this (mm), and by more
#: than :data:`OPENED_SHARE` of the neutral opening: lips 1.5 mm apart, an eye 7 mm
#: open closing by 2.5 mm. On the development scans, dropouts that merge with an eye's
#: hole change it by 0.1 to 0.9 mm; lips parted (AU25) by 2.5 to 4 mm.
OPENED_MM = 1.5
OPENED_SHARE = 0.35
#: Node spacing (mm) of a moved eye's local correction: an upper lid's few millimetres
#: of skin move up to 8 mm as it closes.
LOCAL_SPACING_MM = 2.0
#: How far a local correction reaches, as a multiple of its opening's window: an upper
#: lid's skin moves up to its fold, beyond the window that splits the registrations'
#: data (AU43, development subjects 0-9, registration alone: 0.408 at 1, 0.381 at 2
#: with the bending below).
LOCAL_REACH = 2.0
#: The local correction's bending stiffness and pull toward no correction, relative to a
#: point-to-plane pair of one mm^2, and the weight of a rim pair.
LOCAL_BENDING = 1.0
LOCAL_REST = 0.01
RIM_WEIGHT = 20.0
LOCAL_ITERATIONS = 6
#: How many times a moved eye's correction is fitted, each time with the texture matched
#: again after the expressive image is warped back by the side's motion so far.
LID_TEXTURE_ROUNDS = 2
# Pairs farther than this many robust scales from their target do not pull; the robust
# scale is at least _LOCAL_SCALE_FLOOR_MM.
_LOCAL_TUKEY = 3.0
_LOCAL_SCALE_FLOOR_MM = 0.3


def moved_openings(openings: dict[str, Opening], expressive_grid) -> list[Opening]:
    """The neutral face's openings that the expressive grid (in the same frame) shows
    open by another amount (:data:`OPENED_MM`, :data:`OPENED_SHARE`)."""
    moved = []
    xy = _xy_of(expressive_grid)
    for opening in openings.values():
        seen = opening.seen_in(expressive_grid, xy)
        change = abs(seen.open_mm() - opening.open_mm())
        if change > max(OPENED_MM, OPENED_SHARE * opening.open_mm()):
            moved.append(opening)
    return moved


@dataclass
class LocalCorrection:
    """A correction of a field on one side of an opening: a B-spline field on a fine
    lattice, faded out over :data:`LOCAL_REACH` times the opening's window
    (``opening.sides``)."""

    opening: Opening
    side: str                     # "top" or "bottom"
    lattice: BSplineLattice
    node_values: np.ndarray

    def weight(self, points) -> np.ndarray:
        side, split = self.opening.sides(points, LOCAL_REACH)
        return np.where(side > 0 if self.side == "top" else side < 0, split, 0.0)

    def __call__(self, points) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.zeros(p.shape)
        weight = self.weight(p)
        inside = (weight > 0) & np.isfinite(p).all(axis=1)
        if inside.any():
            out[inside] = self.lattice.evaluate(p[inside, :2], self.node_values) * weight[inside, None]
        return out


def fit_local_correction(opening: Opening, side: str, points, motion, surface: MeshSurface,
                         rim_from=None, rim_to=None, texture_targets=None, texture_weights=None
                         ) -> LocalCorrection | None:
    """Refine ``motion`` on one side of an opening: the data points (k, 3) of the
    neutral face in the opening's window, moved by the motion and the correction, pull
    toward the expressive surface (point-to-plane, Tukey-weighted, none from pairs off
    its rim) and, with texture matches (``texture_targets`` (k, 3), NaN where none,
    and their ``texture_weights``), along it toward where their skin's pattern went;
    the rim points pull toward their targets; the correction's bending and a weak pull
    toward none keep it smooth and local. None without data points."""
    correction = LocalCorrection(opening, side, None, None)
    weight = correction.weight(points)
    inside = weight > 0
    if inside.sum() < 10:
        return None
    data, weight = np.asarray(points, dtype=np.float64)[inside], weight[inside]
    if texture_targets is not None:
        texture_targets = np.asarray(texture_targets, dtype=np.float64)[inside]
        texture_weights = np.where(np.isfinite(texture_targets).all(axis=1),
                                   np.asarray(texture_weights, dtype=np.float64)[inside], 0.0)
        texture_targets = np.nan_to_num(texture_targets)
    lattice = BSplineLattice(data[:, :2].min(axis=0) - 1.0, data[:, :2].max(axis=0) + 1.0, LOCAL_SPACING_MM)
    # the data points' stencils, the system's pattern and its factor's ordering and
    # symbolic analysis once; each iteration fills in values and refactorises
    system = LatticeSystem(lattice, data[:, :2])
    start = motion(data)
    n = lattice.n_nodes
    fixed = LOCAL_BENDING * sp.block_diag([lattice.bending()] * 3) + LOCAL_REST * sp.identity(3 * n)
    fixed_rhs = np.zeros(3 * n)
    if rim_from is not None and len(rim_from):
        # A rim's edge shows how far across the opening it went, not how far it slid
        # along the edge, nor its depth (under a closed eye's rim the scan's surface is
        # the upper lid in front of it): its pairs pull across the chord only; the slide
        # comes from the skin beside it, the depth from the point-to-plane pulls.
        rim_basis = lattice.basis(rim_from[:, :2]).multiply(correction.weight(rim_from)[:, None]).tocsr()
        residual = rim_to - rim_from - motion(rim_from)
        across_chord = np.append(opening.axes()[1], 0.0)
        across = np.outer(across_chord, across_chord)
        fixed = fixed + RIM_WEIGHT * sp.kron(across, rim_basis.T @ rim_basis)
        fixed_rhs = RIM_WEIGHT * np.concatenate([rim_basis.T @ (residual @ across[a]) for a in range(3)])
    fixed_values = system.aligned(fixed)

    normals_of = face_normals(surface.vertices, surface.faces)
    values = np.zeros((n, 3))
    for _ in range(LOCAL_ITERATIONS):
        # the correction at the data points, faded by their weight
        current = weight[:, None] * (system.basis @ values)
        moved = data + start + current
        closest = surface.closest_point(moved)
        normal = normals_of[closest.triangles]
        along = np.einsum("ij,ij->i", closest.points - moved, normal)
        scale = max(1.4826 * float(np.median(np.abs(along))), _LOCAL_SCALE_FLOOR_MM)
        u = np.abs(along) / (_LOCAL_TUKEY * scale)
        pull = np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0) * ~off_surface(along, closest.distances)
        # the correction c: (n . (c - current) - along)^2 and, for a texture match q,
        # |P (c - (q - p - u(p)))|^2 with P = I - n n^T; both linear in the node values
        target = along + np.einsum("ij,ij->i", current, normal)
        blocks = pull[:, None, None] * np.einsum("ia,ib->iab", normal, normal)
        pulled = (pull * target)[:, None] * normal
        if texture_targets is not None:
            wanted = texture_targets - data - start
            tangent = np.eye(3)[None] - np.einsum("ia,ib->iab", normal, normal)
            residual = np.einsum("iab,ib->ia", tangent, wanted - current)
            scale = max(robust_scale(np.linalg.norm(residual, axis=1)[texture_weights > 0]), _LOCAL_SCALE_FLOOR_MM)
            w = texture_weights * tukey_weights(np.linalg.norm(residual, axis=1), _LOCAL_TUKEY * scale)
            blocks = blocks + w[:, None, None] * tangent
            pulled = pulled + w[:, None] * np.einsum("iab,ib->ia", tangent, wanted)
        # a data point's stencil is scaled by its weight: its 3 x 3 block by the square
        data_values = system.data_term(weight[:, None] ** 2 * symmetric_blocks(blocks))
        rhs = np.concatenate([system.basis.T @ (weight * pulled[:, a]) for a in range(3)]) + fixed_rhs
        values = system.solve(fixed_values + data_values, rhs).reshape(3, n).T
    return LocalCorrection(opening, side, lattice, values)


@dataclass
class _Corrected:
    """A field plus local corrections."""

    motion: object
    corrections: list = field(default_factory=list)

    def __call__(self, points) -> np.ndarray:
        out = self.motion(points)
        for correction in self.corrections:
            out = out + correction(points)
        return out


@dataclass
class CutMotion:
    """The motion of a face cut at its moved openings: ``upper`` above each opening's
    line, ``lower`` below it (each a displacement field, (m, 3) points -> (m, 3)).

    Attributes
    ----------
    upper, lower : callable
    openings : list of Opening
        The source face's openings that moved.
    texture : TextureMatches or None
        The texture matches both registrations weighed (None: geometry alone).
    closure : dict
        For each moved eye, how far it closed at each knot of its chord: the share of
        the neutral opening its upper edge travelled (1: shut; negative: opened wider).
    """

    upper: object
    lower: object
    openings: list
    texture: object = None
    closure: dict = field(default_factory=dict)

    def __call__(self, points, share=None) -> np.ndarray:
        """The displacement at points (m, 3); ``share`` (m,) is how much of the upper
        field each point takes (default: by the source's openings,
        :func:`tpscore.face.openings.opening_sides`)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if share is None:
            share = opening_sides(self.openings, p)
        share = np.asarray(share, dtype=np.float64).reshape(-1, 1)
        return share * self.upper(p) + (1.0 - share) * self.lower(p)

    def split(self, each) -> "CutMotion":
        """The same cut with ``each`` applied to both sides' fields (e.g. a mirror average)."""
        return CutMotion(each(self.upper), each(self.lower), self.openings, self.texture, self.closure)


def _xy_of(grid):
    """The grid's :func:`~tpscore.face.openings.grid_xy` (None without valid vertices,
    where no opening shows a hole)."""
    return grid_xy(grid.points, grid.mask) if grid.mask.any() else None


def eye_windows(openings, grid) -> list[np.ndarray]:
    """Each eye's window among the openings, as a mask of the grid: where a moved eye's
    local corrections reach (:data:`LOCAL_REACH` times its window), and where its
    texture is matched at full resolution."""
    return [opening.sides(grid.points, LOCAL_REACH)[1] > 0 for opening in openings if opening.name != "mouth"]


def _side_weights(openings, points) -> tuple[np.ndarray, np.ndarray]:
    """Each point's weight as a data point of the upper and of the lower registration:
    0 on the other side of an opening's line inside its window."""
    upper, lower = np.ones(points.shape[:-1]), np.ones(points.shape[:-1])
    for opening in openings:
        side, split = opening.sides(points)
        upper = np.minimum(upper, np.where(side < 0, 1.0 - split, 1.0))
        lower = np.minimum(lower, np.where(side > 0, 1.0 - split, 1.0))
    return upper, lower


def register_cut(neutral, expressive, openings: list[Opening], register, texture=None,
                 texture_weight: float = 10.0) -> CutMotion:
    """Register a neutral face onto its expressive scan (both NormalisedFace, one frame)
    on each side of the moved openings.

    ``register(weight, landmarks, pairs)`` runs one registration
    (:func:`tpscore.register_surfaces` with the neutral's data-point weights, its
    landmarks with those of the other side removed, and soft pairs) and returns its
    field. Each moved eye's rims pull both sides' local corrections.
    """
    grid = neutral.grid
    surface = expressive.surface()
    weights = _side_weights(openings, grid.points)
    landmark_weight = [w.reshape(-1)[np.maximum(grid.landmark_vertices, 0)] for w in weights]
    expressive_xy = _xy_of(expressive.grid)
    eyes = [opening for opening in openings if opening.name != "mouth"]
    # each moved eye as the expressive scan shows it, and how far it closed
    seen = {opening.name: opening.seen_in(expressive.grid, expressive_xy)
            for opening in eyes}
    closure = {}
    for opening in eyes:
        height = opening.top - opening.bottom
        # a knot where the neutral eye has no height (its corners) gives no share (NaN)
        share = np.divide(opening.top - seen[opening.name].top, height, out=np.full(len(height), np.nan),
                          where=height > 0)
        closure[opening.name] = np.where(np.isfinite(seen[opening.name].top), share, 1.0)
    neutral_xy = _xy_of(grid)
    lid_windows = eye_windows(eyes, grid)

    def one_side(side, weight, keep):
        landmarks = np.where((keep > 0.5)[:, None], neutral.landmarks, np.nan)
        motion = register(weight, landmarks, None)
        corrections = []
        for _ in range(LID_TEXTURE_ROUNDS if eyes else 0):
            side_targets = side_weights = None
            if texture is not None:
                # The flow found again with the expressive image warped back by this
                # side's motion: a lid's skin travels farther than the flow finds alone.
                current = _Corrected(motion, corrections)(grid.points.reshape(-1, 3)).reshape(grid.points.shape)
                side_texture = texture.refined(current, lid_windows)
                side_targets = side_texture.targets[grid.mask]
                side_weights = texture_weight * side_texture.confidence[grid.mask]
            corrections = _lid_corrections(eyes, seen, side, neutral, neutral_xy, expressive, surface, motion,
                                           side_targets, side_weights)
        return _Corrected(motion, corrections) if corrections else motion

    # the two sides share nothing they change: each on its own thread (their
    # registrations' kernels release the GIL)
    upper, lower = side_by_side(lambda: one_side("top", weights[0], landmark_weight[0]),
                                lambda: one_side("bottom", weights[1], landmark_weight[1]))
    return CutMotion(upper, lower, list(openings), texture, closure)


def _lid_corrections(eyes, seen, side, neutral, neutral_xy, expressive, surface, motion, texture_targets,
                     texture_weights):
    """Each moved eye's local correction of one side's motion, pulled by where its rim
    went (``seen``: each eye as the expressive scan shows it) and by the texture
    matches."""
    grid = neutral.grid
    corrections = []
    for opening in eyes:
        rim_from = grid.points.reshape(-1, 3)[opening.rim(grid, side, neutral_xy)]
        rim_to = _onto(surface, opening.rim_targets(rim_from, seen[opening.name], side), expressive.grid.points)
        found = np.isfinite(rim_to).all(axis=1)
        correction = fit_local_correction(opening, side, grid.points[grid.mask], motion, surface,
                                          rim_from[found], rim_to[found], texture_targets, texture_weights)
        if correction is not None:
            corrections.append(correction)
    return corrections


#: Knots of an opening's chord at which its edges pair two faces (away from the corners,
#: which are landmarks already).
EDGE_KNOTS = np.linspace(0.15, 0.85, 8)
# An edge point is taken this far (mm) from the hole into the skin, where the surface is.
_EDGE_INSET_MM = 0.7


def opening_pairs(openings_a: dict, face_a, openings_b: dict, face_b, names) -> tuple[np.ndarray, np.ndarray]:
    """Corresponding points of two faces along their openings of the given names: the
    upper and lower edges of each hole at the same share of the chord (the line, for
    a closed mouth), on each face's surface. They join the landmarks in the map
    between the faces, so that an upper lid or lip meets its counterpart: the motion
    at an opening changes over a millimetre or two."""
    pairs_a, pairs_b = [], []
    for name in names:
        if name not in openings_a or name not in openings_b:
            continue
        one, other = openings_a[name], openings_b[name]
        for edge, inset in (("top", _EDGE_INSET_MM), ("bottom", -_EDGE_INSET_MM)):
            b_one = _at_knots(one, edge, EDGE_KNOTS)
            b_other = _at_knots(other, edge, EDGE_KNOTS)
            if not (np.isfinite(b_one).any() and np.isfinite(b_other).any()):
                if edge == "bottom":
                    continue
                b_one, b_other = one.line_at(EDGE_KNOTS), other.line_at(EDGE_KNOTS)  # closed: the line
                inset = 0.0
            pa = _onto(face_a.surface(), one.points_at(EDGE_KNOTS, b_one + inset), face_a.grid.points)
            pb = _onto(face_b.surface(), other.points_at(EDGE_KNOTS, b_other + inset), face_b.grid.points)
            found = np.isfinite(pa).all(axis=1) & np.isfinite(pb).all(axis=1)
            pairs_a.append(pa[found])
            pairs_b.append(pb[found])
    if not pairs_a:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(pairs_a), np.concatenate(pairs_b)


def _at_knots(opening: Opening, edge: str, knots) -> np.ndarray:
    values = opening.top if edge == "top" else opening.bottom
    known = np.isfinite(values)
    if known.sum() < 2:
        return np.full(len(knots), np.nan)
    inside = (knots >= opening.knots[known][0]) & (knots <= opening.knots[known][-1])
    return np.where(inside, np.interp(knots, opening.knots[known], values[known]), np.nan)


def _onto(surface: MeshSurface, xy, points) -> np.ndarray:
    """The surface's point under each x, y (a ray along -z; NaN where it misses or x, y
    is NaN)."""
    top = float(np.nanmax(points[..., 2])) + 100.0
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    out = np.full((len(xy), 3), np.nan)
    known = np.isfinite(xy).all(axis=1)
    if known.any():
        hits = surface.intersect_rays(np.column_stack([xy[known], np.full(int(known.sum()), top)]),
                                      np.tile([0.0, 0.0, -1.0], (int(known.sum()), 1)))
        out[known] = np.where(hits.hit[:, None], hits.points, np.nan)
    return out

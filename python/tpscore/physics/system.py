"""The arrays that define a skin system, validated once, and the compiled system built
from them.

:class:`SkinArrays` is the complete description the compiled core
(:func:`tpscore.skin_sim.compiled_skin_system`) and the NumPy reference (:mod:`tpscore.reference.skin`)
share: particles and masses; biphasic damped springs; anchors to the skull or the
mandible; muscles with their particles and weights; the skull for contact; the jaw's
axis. :mod:`tpscore.physics.layers` fills it from a head; tests build small ones by
hand (one spring, a chain).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..skin_sim import INTEGRATORS, compiled_skin_system

__all__ = ["SkinArrays", "SKULL", "MANDIBLE", "LINEAR", "SPHINCTER", "INTEGRATORS", "rim_edges"]

SKULL, MANDIBLE = 0, 1
LINEAR, SPHINCTER = 0, 1


def _float(array, shape, name):
    try:
        out = np.ascontiguousarray(array, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be numeric: {exc}") from None
    if out.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {out.shape}")
    if out.size and not np.isfinite(out).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    return out


def _index(array, shape, name, upper, *, allow_negative=False):
    out = np.asarray(array)
    if out.size and not np.issubdtype(out.dtype, np.integer):
        raise ValueError(f"{name} must hold integers, got dtype {out.dtype}")
    out = np.ascontiguousarray(out, dtype=np.int64)
    if out.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {out.shape}")
    low = -1 if allow_negative else 0
    if out.size and (out.min() < low or out.max() >= upper):
        raise ValueError(f"{name} must lie in [{low}, {upper}), got [{out.min()}, {out.max()}]")
    return out


def rim_edges(faces: np.ndarray, n: int, bones=None) -> np.ndarray:
    """Per triangle (f,), bit k set when the edge opposite corner k is on the rim: in no
    other triangle (of the same bone, when per-vertex ``bones`` are given; a triangle
    whose corners lie on different bones belongs to none and gets no bits)."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    group = np.zeros(len(faces), dtype=np.int64)
    if bones is not None:
        corner_bones = np.asarray(bones)[faces]
        uniform = np.all(corner_bones == corner_bones[:, :1], axis=1)
        group = np.where(uniform, corner_bones[:, 0], -1)
    opposite = [faces[:, [1, 2]], faces[:, [2, 0]], faces[:, [0, 1]]]
    # an edge key that also carries the triangle's bone, so bones do not share edges
    codes = [(np.sort(e, axis=1) @ np.array([n + 1, 1])) * 4 + (group + 1) for e in opposite]
    unique, counts = np.unique(np.concatenate(codes), return_counts=True)
    single = unique[counts == 1]
    rim = np.zeros(len(faces), dtype=np.int64)
    for k, code in enumerate(codes):
        rim |= np.isin(code, single).astype(np.int64) << k
    rim[group < 0] = 0
    return rim


@dataclass(frozen=True, eq=False)
class SkinArrays:
    """Everything that defines a skin system (units: mm, g, s; forces in g mm / s^2).

    Shapes: n particles, s springs, a anchors, k muscles, v skull vertices. Every
    array is converted and checked by :meth:`validated`; the compiled core assumes that
    was done.

    Attributes
    ----------
    masses : (n,) > 0
    spring_first, spring_second : (s,) int
        The particles each spring joins (different).
    spring_rest : (s,) > 0
        Rest lengths.
    spring_stiffness, spring_stiffness_high : (s,) >= 0
        Slopes of the biphasic law below and beyond the knee (high >= low).
    spring_knee : (s,) >= 0
        Knee strain |l - l0| / l0 where the slope changes.
    spring_damping : (s,) >= 0
        Damping along the spring.
    anchor_particle : (a,) int
    anchor_target : (a, 3)
        Rest position of each anchor point, fixed to ``anchor_bone`` (SKULL or MANDIBLE).
    anchor_stiffness, anchor_damping : (a,) >= 0
    drag : float >= 0
        Mass-proportional damping rate (1/s).
    muscle_kind, muscle_bone : (k,) int
        LINEAR or SPHINCTER; SKULL or MANDIBLE.
    muscle_point : (k, 3)
        Attachment (linear) or epicentre (sphincter).
    muscle_axes : (k, 6)
        A sphincter's two unit axes (zeros for a linear muscle).
    muscle_max_force : (k,) >= 0
        Total force at contraction 1.
    muscle_indptr : (k + 1,), muscle_particles, muscle_weights : (e,)
        CSR list of each muscle's particles and weights (a muscle's weights sum to 1).
    skull_vertices, skull_normals : (v, 3)
        Skull vertices at rest and their unit outward normals.
    skull_faces : (f, 3) int
        The skull's triangles, oriented outward.
    skull_face_indptr : (v + 1,), skull_vertex_faces : (e,)
        CSR list of the triangles around each skull vertex.
    skull_face_rim : (f,) int
        Per triangle, bit k set when the edge opposite corner k is on the skull's rim
        (in one triangle only).
    skull_bone : (v,) int
    skull_indptr : (v + 1,), skull_neighbours : (e,)
        CSR vertex adjacency of the skull mesh.
    particle_foot : (n,) int
        First skull vertex of each particle's contact search; -1: no contact.
    contact_stiffness, contact_damping : (n,) >= 0
        Stiffness and damping of the contact penalty per particle (0: projection only).
    contact_margin : (n,) >= 0
        Height over the skull below which the penalty pushes each particle out.
    jaw_pivot : (3,), jaw_axis : (3,) unit
    """

    masses: np.ndarray
    spring_first: np.ndarray
    spring_second: np.ndarray
    spring_rest: np.ndarray
    spring_stiffness: np.ndarray
    spring_stiffness_high: np.ndarray
    spring_knee: np.ndarray
    spring_damping: np.ndarray
    anchor_particle: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    anchor_target: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    anchor_bone: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    anchor_stiffness: np.ndarray = field(default_factory=lambda: np.zeros(0))
    anchor_damping: np.ndarray = field(default_factory=lambda: np.zeros(0))
    drag: float = 0.0
    muscle_kind: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    muscle_bone: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    muscle_point: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    muscle_axes: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    muscle_max_force: np.ndarray = field(default_factory=lambda: np.zeros(0))
    muscle_indptr: np.ndarray = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    muscle_particles: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    muscle_weights: np.ndarray = field(default_factory=lambda: np.zeros(0))
    skull_vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    skull_normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    skull_faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))
    skull_face_indptr: np.ndarray | None = None
    skull_vertex_faces: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    skull_face_rim: np.ndarray | None = None
    skull_bone: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    skull_indptr: np.ndarray = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    skull_neighbours: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    particle_foot: np.ndarray | None = None
    contact_stiffness: np.ndarray | None = None
    contact_damping: np.ndarray | None = None
    contact_margin: np.ndarray | float = 0.0
    jaw_pivot: np.ndarray = field(default_factory=lambda: np.zeros(3))
    jaw_axis: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))

    @property
    def particles(self) -> int:
        return len(self.masses)

    @property
    def muscles(self) -> int:
        return len(self.muscle_kind)

    def validated(self) -> "SkinArrays":
        """A copy with every array converted to its canonical type and checked.

        Raises
        ------
        ValueError
            Naming the first field that is malformed.
        """
        masses = _float(self.masses, np.shape(self.masses), "masses")
        if masses.ndim != 1 or len(masses) == 0 or not (masses > 0).all():
            raise ValueError("masses must be a non-empty 1-D array of values > 0")
        n = len(masses)
        s = len(np.asarray(self.spring_first).reshape(-1))
        first = _index(self.spring_first, (s,), "spring_first", n)
        second = _index(self.spring_second, (s,), "spring_second", n)
        if np.any(first == second):
            raise ValueError(f"a spring joins particle {first[first == second][0]} to itself")
        out = dict(masses=masses, spring_first=first, spring_second=second)
        for name in ("spring_rest", "spring_stiffness", "spring_stiffness_high", "spring_knee", "spring_damping"):
            out[name] = _float(getattr(self, name), (s,), name)
            if np.any(out[name] < 0):
                raise ValueError(f"{name} must be >= 0")
        if np.any(out["spring_rest"] <= 0):
            raise ValueError("spring_rest must be > 0 (a spring of zero length has no direction)")
        if np.any(out["spring_stiffness_high"] < out["spring_stiffness"]):
            raise ValueError("spring_stiffness_high must be >= spring_stiffness (the law stiffens)")
        a = len(np.asarray(self.anchor_particle).reshape(-1))
        out["anchor_particle"] = _index(self.anchor_particle, (a,), "anchor_particle", n)
        out["anchor_target"] = _float(self.anchor_target, (a, 3), "anchor_target")
        out["anchor_bone"] = _index(self.anchor_bone, (a,), "anchor_bone", 2)
        for name in ("anchor_stiffness", "anchor_damping"):
            out[name] = _float(getattr(self, name), (a,), name)
            if np.any(out[name] < 0):
                raise ValueError(f"{name} must be >= 0")
        drag = float(self.drag)
        if not np.isfinite(drag) or drag < 0:
            raise ValueError(f"drag must be finite and >= 0, got {self.drag!r}")
        out["drag"] = drag
        k = len(np.asarray(self.muscle_kind).reshape(-1))
        out["muscle_kind"] = _index(self.muscle_kind, (k,), "muscle_kind", 2)
        out["muscle_bone"] = _index(self.muscle_bone, (k,), "muscle_bone", 2)
        out["muscle_point"] = _float(self.muscle_point, (k, 3), "muscle_point")
        out["muscle_axes"] = _float(self.muscle_axes, (k, 6), "muscle_axes")
        out["muscle_max_force"] = _float(self.muscle_max_force, (k,), "muscle_max_force")
        if np.any(out["muscle_max_force"] < 0):
            raise ValueError("muscle_max_force must be >= 0")
        indptr = np.ascontiguousarray(self.muscle_indptr, dtype=np.int64)
        if indptr.shape != (k + 1,) or indptr[0] != 0 or np.any(np.diff(indptr) < 0):
            raise ValueError(f"muscle_indptr must be a nondecreasing (k + 1,) = ({k + 1},) array from 0")
        e = int(indptr[-1])
        out["muscle_indptr"] = indptr
        out["muscle_particles"] = _index(self.muscle_particles, (e,), "muscle_particles", n)
        out["muscle_weights"] = _float(self.muscle_weights, (e,), "muscle_weights")
        if np.any(out["muscle_weights"] < 0):
            raise ValueError("muscle_weights must be >= 0")
        sphincter = out["muscle_kind"] == SPHINCTER
        if sphincter.any():
            axes = out["muscle_axes"][sphincter].reshape(-1, 2, 3)
            if not np.allclose(np.linalg.norm(axes, axis=2), 1.0, atol=1e-9):
                raise ValueError("muscle_axes of a sphincter must be two unit vectors")
        v = len(np.asarray(self.skull_vertices).reshape(-1, 3))
        out["skull_vertices"] = _float(self.skull_vertices, (v, 3), "skull_vertices")
        out["skull_normals"] = _float(self.skull_normals, (v, 3), "skull_normals")
        if v and not np.allclose(np.linalg.norm(out["skull_normals"], axis=1), 1.0, atol=1e-9):
            raise ValueError("skull_normals must be unit vectors")
        out["skull_bone"] = _index(self.skull_bone, (v,), "skull_bone", 2)
        f = len(np.asarray(self.skull_faces).reshape(-1, 3))
        out["skull_faces"] = _index(np.asarray(self.skull_faces).reshape(-1, 3), (f, 3), "skull_faces", max(v, 1))
        face_indptr = np.zeros(v + 1, dtype=np.int64) if self.skull_face_indptr is None else \
            np.ascontiguousarray(self.skull_face_indptr, dtype=np.int64)
        if face_indptr.shape != (v + 1,) or face_indptr[0] != 0 or np.any(np.diff(face_indptr) < 0):
            raise ValueError(f"skull_face_indptr must be a nondecreasing ({v + 1},) array from 0")
        out["skull_face_indptr"] = face_indptr
        out["skull_vertex_faces"] = _index(self.skull_vertex_faces, (int(face_indptr[-1]),), "skull_vertex_faces",
                                           max(f, 1))
        rim = np.zeros(f, dtype=np.int64) if self.skull_face_rim is None else self.skull_face_rim
        out["skull_face_rim"] = _index(rim, (f,), "skull_face_rim", 8)
        skull_indptr = np.ascontiguousarray(self.skull_indptr, dtype=np.int64)
        if skull_indptr.shape != (v + 1,) or skull_indptr[0] != 0 or np.any(np.diff(skull_indptr) < 0):
            raise ValueError(f"skull_indptr must be a nondecreasing ({v + 1},) array from 0")
        out["skull_indptr"] = skull_indptr
        out["skull_neighbours"] = _index(self.skull_neighbours, (int(skull_indptr[-1]),), "skull_neighbours",
                                         max(v, 1))
        foot = np.full(n, -1, dtype=np.int64) if self.particle_foot is None else self.particle_foot
        out["particle_foot"] = _index(foot, (n,), "particle_foot", max(v, 1), allow_negative=True)
        if v == 0 and np.any(out["particle_foot"] >= 0):
            raise ValueError("particle_foot refers to skull vertices, but there is no skull")
        for name in ("contact_stiffness", "contact_damping"):
            value = getattr(self, name)
            out[name] = _float(np.zeros(n) if value is None else value, (n,), name)
            if np.any(out[name] < 0):
                raise ValueError(f"{name} must be >= 0")
        margin = np.broadcast_to(np.asarray(self.contact_margin, dtype=np.float64), (n,))
        out["contact_margin"] = _float(margin, (n,), "contact_margin")
        if np.any(out["contact_margin"] < 0):
            raise ValueError("contact_margin must be >= 0")
        out["jaw_pivot"] = _float(self.jaw_pivot, (3,), "jaw_pivot")
        axis = _float(self.jaw_axis, (3,), "jaw_axis")
        if not np.isclose(np.linalg.norm(axis), 1.0, atol=1e-9):
            raise ValueError("jaw_axis must be a unit vector")
        out["jaw_axis"] = axis
        return SkinArrays(**out)

    def core(self):
        """The compiled system (``tpscore._core.SkinSystem``) of validated arrays."""
        return compiled_skin_system(self)

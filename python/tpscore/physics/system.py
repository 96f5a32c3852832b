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
from typing import NamedTuple

import numpy as np

from ..skin_sim import INTEGRATORS, compiled_skin_system

__all__ = ["SkinArrays", "SKIN_FIELDS", "SKULL", "MANDIBLE", "LINEAR", "SPHINCTER", "INTEGRATORS", "rim_edges"]

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


#: Dataclass defaults of :data:`SKIN_FIELDS`: no default, or an empty array of the
#: field's shape.
REQUIRED, EMPTY = "required", "empty"


class SkinField(NamedTuple):
    """One field of :class:`SkinArrays`, as :data:`SKIN_FIELDS` lists it.

    ``kind`` is "float" (float64, finite), "index" (int64 in ``[0, upper)``, or from -1
    with ``allow_negative``), "indptr" (int64 CSR offsets: nondecreasing from 0) or
    "scalar" (a finite float). ``shape`` holds numbers and size letters: n particles,
    s springs, a anchors, k muscles, e a muscle's entries, v skull vertices, f skull
    triangles, t the triangles' entries, u the neighbours' entries, p prisms, "k + 1" one more
    than k; None is the array's own shape. A field with ``sizes`` defines that letter
    (its length; an indptr's last entry). ``reshape``: any array of the right number of
    entries will do; ``broadcast``: a number stands for every row. ``default`` is the
    dataclass default; a field left None is filled with ``missing``.
    """

    name: str
    kind: str
    shape: tuple | None
    doc: str
    upper: int | str | None = None
    nonnegative: bool = False
    sizes: str | None = None
    default: object = EMPTY
    missing: float | None = None
    allow_negative: bool = False
    reshape: bool = False
    broadcast: bool = False


_F = SkinField
#: The fields of a skin system, listed once: :class:`SkinArrays` is built from this table,
#: validated by it and handed to the compiled core by it (whose own list is
#: ``TPSCORE_SKIN_FIELDS`` in ``cpp/include/tpscore/skin_sim.hpp``, in the same order).
SKIN_FIELDS = (
    _F("masses", "float", None, "Particle masses (> 0, at least one).", default=REQUIRED),
    _F("spring_first", "index", ("s",), "The particles each spring joins (different).", "n", sizes="s",
       default=REQUIRED),
    _F("spring_second", "index", ("s",), "", "n", default=REQUIRED),
    _F("spring_rest", "float", ("s",), "Rest lengths (> 0).", nonnegative=True, default=REQUIRED),
    _F("spring_stiffness", "float", ("s",), "Slope of the biphasic law below the knee.", nonnegative=True,
       default=REQUIRED),
    _F("spring_stiffness_high", "float", ("s",), "Slope beyond the knee (>= spring_stiffness).", nonnegative=True,
       default=REQUIRED),
    _F("spring_knee", "float", ("s",), "Knee strain |l - l0| / l0 where the slope changes.", nonnegative=True,
       default=REQUIRED),
    _F("spring_damping", "float", ("s",), "Damping along the spring.", nonnegative=True, default=REQUIRED),
    _F("anchor_particle", "index", ("a",), "", "n", sizes="a"),
    _F("anchor_target", "float", ("a", 3), "Rest position of each anchor point, fixed to anchor_bone."),
    _F("anchor_bone", "index", ("a",), "SKULL or MANDIBLE.", 2),
    _F("anchor_stiffness", "float", ("a",), "", nonnegative=True),
    _F("anchor_damping", "float", ("a",), "", nonnegative=True),
    _F("drag", "scalar", (), "Mass-proportional damping rate (1/s), >= 0.", default=0.0),
    _F("muscle_kind", "index", ("k",), "LINEAR or SPHINCTER.", 2, sizes="k"),
    _F("muscle_bone", "index", ("k",), "SKULL or MANDIBLE.", 2),
    _F("muscle_point", "float", ("k", 3), "Attachment (linear) or epicentre (sphincter)."),
    _F("muscle_axes", "float", ("k", 6), "A sphincter's two unit axes (zeros for a linear muscle)."),
    _F("muscle_max_force", "float", ("k",), "Total force at contraction 1.", nonnegative=True),
    _F("muscle_indptr", "indptr", ("k + 1",), "CSR rows of each muscle's particles and weights.", sizes="e"),
    _F("muscle_particles", "index", ("e",), "", "n"),
    _F("muscle_weights", "float", ("e",), "A muscle's weights sum to 1.", nonnegative=True),
    _F("skull_vertices", "float", ("v", 3), "Skull vertices at rest.", sizes="v"),
    _F("skull_normals", "float", ("v", 3), "Their unit outward normals."),
    _F("skull_faces", "index", ("f", 3), "The skull's triangles, oriented outward.", "v", sizes="f", reshape=True),
    _F("skull_face_indptr", "indptr", ("v + 1",), "CSR list of the triangles around each skull vertex.",
       sizes="t", default=None, missing=0),
    _F("skull_vertex_faces", "index", ("t",), "", "f"),
    _F("skull_face_rim", "index", ("f",), "Per triangle, bit k set when the edge opposite corner k is on the "
       "skull's rim (in one triangle only).", 8, default=None, missing=0),
    _F("skull_bone", "index", ("v",), "SKULL or MANDIBLE per skull vertex.", 2),
    _F("skull_indptr", "indptr", ("v + 1",), "CSR vertex adjacency of the skull mesh.", sizes="u"),
    _F("skull_neighbours", "index", ("u",), "", "v"),
    _F("particle_foot", "index", ("n",), "First skull vertex of each particle's contact search; -1: no contact.",
       "v", default=None, missing=-1, allow_negative=True),
    _F("contact_stiffness", "float", ("n",), "Stiffness of the contact penalty per particle (0: projection only).",
       nonnegative=True, default=None, missing=0.0),
    _F("contact_damping", "float", ("n",), "Damping of the contact penalty per particle.", nonnegative=True,
       default=None, missing=0.0),
    _F("contact_margin", "float", ("n",), "Height over the skull below which the penalty pushes each particle out "
       "(a number: the same for all).", nonnegative=True, default=0.0, broadcast=True),
    _F("jaw_pivot", "float", (3,), "A point on the jaw's axis."),
    _F("jaw_axis", "float", (3,), "The jaw's unit axis.", default=(1.0, 0.0, 0.0)),
    _F("prism_particles", "index", ("p", 6), "Prisms of tissue that keep their volume: a triangle's three particles, "
       "then the three below them (six different particles).", "n", sizes="p", reshape=True),
    _F("prism_rest_volume", "float", ("p",), "Each prism's volume at rest, positive (three tetrahedra: a b c A, "
       "b c A B, c A B C)."),
    _F("prism_stiffness", "float", ("p",), "k of each prism's energy k (V - V0)^2 / 2.", nonnegative=True),
)
del _F


def _dimension(term, sizes) -> int:
    """A number of a shape rule: a number, a size letter or "letter + 1"."""
    if isinstance(term, int):
        return term
    letter, _, plus = term.partition(" + ")
    return sizes[letter] + (int(plus) if plus else 0)


def _default(spec: SkinField):
    """The dataclass default of a field: an empty array of its shape, or its value."""
    if spec.default is REQUIRED:
        return field()
    if spec.default is EMPTY:
        dtype = np.float64 if spec.kind == "float" else np.int64
        shape = tuple(_dimension(term, {letter: 0 for letter in "nsakevftup"}) for term in spec.shape)
        return field(default_factory=lambda: np.zeros(shape, dtype=dtype))
    if isinstance(spec.default, tuple):
        return field(default_factory=lambda: np.array(spec.default))
    return field(default=spec.default)


def _shape_text(spec: SkinField) -> str:
    """A field's shape and type as its documentation spells it: "(s,) int"."""
    if spec.kind == "scalar":
        return "float"
    dims = [str(term) for term in spec.shape or ("n",)]
    text = "(" + ", ".join(dims) + ("," if len(dims) == 1 else "") + ")"
    return text + (" int" if spec.kind in ("index", "indptr") else "")


def _attributes_doc() -> str:
    """The numpydoc Attributes section of :class:`SkinArrays`, from the table."""
    lines = []
    for spec in SKIN_FIELDS:
        lines.append(f"    {spec.name} : {_shape_text(spec)}")
        if spec.doc:
            lines.append(f"        {spec.doc}")
    return "\n".join(lines)


def _with_skin_fields(cls):
    """Give the class one dataclass field per row of :data:`SKIN_FIELDS`."""
    cls.__annotations__ = {spec.name: "float" if spec.kind == "scalar" else "np.ndarray" for spec in SKIN_FIELDS}
    for spec in SKIN_FIELDS:
        setattr(cls, spec.name, _default(spec))
    if cls.__doc__:  # None under python -OO
        cls.__doc__ = cls.__doc__.replace("{attributes}", _attributes_doc())
    return cls


def _check_field(spec: SkinField, value, sizes):
    """One field converted to its canonical type and checked, as its row says."""
    if spec.kind == "scalar":
        number = float(value)
        if not np.isfinite(number) or number < 0:
            raise ValueError(f"{spec.name} must be finite and >= 0, got {value!r}")
        return number
    if spec.sizes and spec.kind != "indptr":
        try:
            flat = np.asarray(value).reshape((-1,) + tuple(spec.shape[1:]))
        except ValueError:
            raise ValueError(f"{spec.name} must have shape {spec.shape}, got {np.shape(value)}") from None
        sizes[spec.sizes] = len(flat)
        value = flat if spec.reshape else value
    shape = None if spec.shape is None else tuple(_dimension(term, sizes) for term in spec.shape)
    if value is None and spec.missing is not None:
        value = np.full(shape, spec.missing, dtype=np.float64 if spec.kind == "float" else np.int64)
    if spec.kind == "float":
        if spec.broadcast:
            value = np.broadcast_to(np.asarray(value, dtype=np.float64), shape)
        out = _float(value, np.shape(value) if shape is None else shape, spec.name)
        if spec.nonnegative and np.any(out < 0):
            raise ValueError(f"{spec.name} must be >= 0")
        return out
    if spec.kind == "indptr":
        out = np.ascontiguousarray(value, dtype=np.int64)
        if out.shape != shape or out[0] != 0 or np.any(np.diff(out) < 0):
            raise ValueError(f"{spec.name} must be a nondecreasing ({spec.shape[0]},) = {shape} array from 0")
        sizes[spec.sizes] = int(out[-1])
        return out
    upper = spec.upper if isinstance(spec.upper, int) else max(sizes[spec.upper], 1)
    return _index(value, shape, spec.name, upper, allow_negative=spec.allow_negative)


def _check_relations(name: str, out: dict) -> None:
    """The checks that relate a field to others, run once the named field is checked."""
    if name == "masses":
        masses = out["masses"]
        if masses.ndim != 1 or len(masses) == 0 or not (masses > 0).all():
            raise ValueError("masses must be a non-empty 1-D array of values > 0")
    elif name == "spring_second":
        first, second = out["spring_first"], out["spring_second"]
        if np.any(first == second):
            raise ValueError(f"a spring joins particle {first[first == second][0]} to itself")
    elif name == "spring_damping":
        if np.any(out["spring_rest"] <= 0):
            raise ValueError("spring_rest must be > 0 (a spring of zero length has no direction)")
        if np.any(out["spring_stiffness_high"] < out["spring_stiffness"]):
            raise ValueError("spring_stiffness_high must be >= spring_stiffness (the law stiffens)")
    elif name == "muscle_weights":
        sphincter = out["muscle_kind"] == SPHINCTER
        if sphincter.any():
            axes = out["muscle_axes"][sphincter].reshape(-1, 2, 3)
            if not np.allclose(np.linalg.norm(axes, axis=2), 1.0, atol=1e-9):
                raise ValueError("muscle_axes of a sphincter must be two unit vectors")
    elif name == "skull_normals":
        normals = out["skull_normals"]
        if len(normals) and not np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9):
            raise ValueError("skull_normals must be unit vectors")
    elif name == "particle_foot":
        if len(out["skull_vertices"]) == 0 and np.any(out["particle_foot"] >= 0):
            raise ValueError("particle_foot refers to skull vertices, but there is no skull")
    elif name == "jaw_axis":
        if not np.isclose(np.linalg.norm(out["jaw_axis"]), 1.0, atol=1e-9):
            raise ValueError("jaw_axis must be a unit vector")
    elif name == "prism_particles":
        corners = np.sort(out["prism_particles"], axis=1)
        if np.any(corners[:, 1:] == corners[:, :-1]):
            bad = int(np.flatnonzero(np.any(corners[:, 1:] == corners[:, :-1], axis=1))[0])
            raise ValueError(f"prism_particles: prism {bad} uses a particle twice")
    elif name == "prism_rest_volume":
        if np.any(out["prism_rest_volume"] <= 0):
            raise ValueError("prism_rest_volume must be > 0 (order each prism's corners so that its volume is "
                             "positive at rest)")


@dataclass(frozen=True, eq=False)
@_with_skin_fields
class SkinArrays:
    """Everything that defines a skin system (units: mm, g, s; forces in g mm / s^2).

    Shapes: n particles, s springs, a anchors, k muscles, v skull vertices, f skull
    triangles, p prisms; e, t and u count the entries of the CSR lists. Every array is converted
    and checked by :meth:`validated`; the compiled core assumes that was done. The
    fields are the rows of :data:`SKIN_FIELDS`.

    Attributes
    ----------
{attributes}
    """

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
        out, sizes = {}, {}
        for spec in SKIN_FIELDS:
            out[spec.name] = _check_field(spec, getattr(self, spec.name), sizes)
            if spec.name == "masses":
                sizes["n"] = len(out["masses"]) if out["masses"].ndim else 0
            _check_relations(spec.name, out)
        return SkinArrays(**out)

    def core(self):
        """The compiled system (``tpscore._core.SkinSystem``) of validated arrays."""
        return compiled_skin_system(self)

"""The three layers of the skin and the springs between them.

The epidermal layer is the head's skin mesh. The dermal and the hypodermal layers are
copies of it moved toward the skull along each vertex's line to its skull vertex (the
ray toward the head's geometric centre on the template), to fractions
``dermal_depth`` and ``hypodermal_depth`` of the soft-tissue depth. Particles are
numbered layer by layer: epidermis 0..n-1, dermis n..2n-1, hypodermis 2n..3n-1.

Springs, all biphasic and damped:

- *in a layer*, along every mesh edge: a membrane. The epidermal one is the skin
  proper (``skin_modulus_kpa`` over ``skin_thickness_mm``); the two lower ones carry
  the in-plane stiffness of half of each slab they bound.
- *between layers*, from each vertex to the same vertex below (compression and
  tension through the slab) and to the ends of its edges below (shear). The dermal
  slab (epidermis to dermis) is soft -- highly deformable -- and the hypodermal slab
  (dermis to hypodermis, the fat and the muscles) stiffer.
- *anchors*: each hypodermal particle is tied to its rest position by the loose tissue
  over the bone; the mandible carries the anchors of its vertices.

Volume: each skin triangle with the same triangle in the layer below bounds a prism of
tissue (two per triangle: the dermal and the hypodermal slab), which resists a change
of its volume V with energy K (V - V0)^2 / (2 V0), K the slab's bulk modulus
(``bulk_ratio`` times its Young's modulus). Soft tissue is nearly incompressible:
squeezed in its plane, as beside a smiling mouth's corner, it thickens and the skin
bulges out, where springs alone let it fold in place.

The hypodermal layer rests on the skull: its particles meet it (a damped penalty
within ``contact_margin_mm``, and a projection back onto the skull of any that get
inside). The layers above reach the skull only if a column inverts, which the
simulation detects and refuses.

Stiffnesses come from moduli, so they do not depend on the mesh resolution: a spring
that stands for a volume V of tissue of modulus E over length L has k = E V / L^2 (a
column of area A and height t: E A / t). Shear springs share a slab's shear modulus
E / 3 (incompressible tissue) among the springs of each column. Every spring is
damped at ``damping_ratio`` of its own critical damping, and masses are the tissue's
density times the volume each particle stands for.

Units: mm, g, s; 1 kPa = 1e3 g / (mm s^2); forces in g mm / s^2 (1 N = 1e6).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from .._validation import check_options
from ..mesh import vertex_normals, voronoi_areas
from .linearised import oriented_prisms
from .muscles import SkinLinearMuscle, muscle_weights
from .system import LINEAR, MANDIBLE, SKULL, SPHINCTER, SkinArrays, rim_edges

__all__ = ["SkinMaterial", "SkinLayers", "build_layers", "NEWTON", "KPA"]

#: One newton in g mm / s^2.
NEWTON = 1e6
#: One kilopascal in g / (mm s^2).
KPA = 1e3


@dataclass(frozen=True)
class SkinMaterial:
    """Mechanical parameters of the layered skin (defaults: adult facial soft tissue,
    round values from the ranges reported for in-vivo indentation and suction tests).

    Attributes
    ----------
    skin_modulus_kpa : float
        Young's modulus of the skin proper (epidermis and dermis) in its plane.
    skin_thickness_mm : float
        Its thickness.
    dermal_modulus_kpa : float
        The dermal slab under the skin (dermis to subcutaneous fat): highly deformable.
    hypodermal_modulus_kpa : float
        The hypodermal slab (fat, fascia and the mimic muscles).
    anchor_modulus_kpa : float
        The loose tissue that ties the hypodermis to the bone, over the rest of the depth.
    dermal_depth, hypodermal_depth : float
        Depth of the dermal and hypodermal layers as fractions of the soft-tissue depth.
    knee_strain : float
        Strain where each spring's slope rises (the biphasic law).
    stiffening : float
        Ratio of the slope beyond the knee to the slope below it (>= 1).
    damping_ratio : float
        Each spring's damping as a fraction of its critical damping.
    drag : float
        Mass-proportional damping (1/s) on every particle: soft tissue is heavily
        damped (a face does not ring), and with a velocity that halves in about 5 ms
        the skin settles within about 100 ms of the end of a 30 ms ramp.
    density_g_mm3 : float
        Tissue density.
    flexion : float
        Stiffness of the skin's flexion springs (across each pair of triangles) as a
        fraction of its membrane stiffness; resists folding at the mesh's scale.
    contact_margin_mm : float
        Height over the skull's tangent plane below which the contact penalty pushes a
        particle out.
    contact_stiffness : float
        The penalty's stiffness as a multiple of the particle's own stiffness at rest
        (the sum of its springs' and anchor's slopes).
    bulk_ratio : float
        Each slab's bulk modulus as a multiple of its Young's modulus: how strongly a
        prism of tissue keeps its volume (0: not at all). Incompressible tissue has a
        bulk modulus far above its Young's; the value is kept where the explicit
        integrator's stable step does not shrink much.
    """

    skin_modulus_kpa: float = 20.0
    skin_thickness_mm: float = 1.5
    dermal_modulus_kpa: float = 20.0
    hypodermal_modulus_kpa: float = 30.0
    anchor_modulus_kpa: float = 1.0
    dermal_depth: float = 0.3
    hypodermal_depth: float = 0.85
    knee_strain: float = 0.3
    stiffening: float = 4.0
    damping_ratio: float = 0.3
    drag: float = 150.0
    density_g_mm3: float = 1.05e-3
    flexion: float = 3.0
    contact_margin_mm: float = 0.5
    contact_stiffness: float = 2.0
    bulk_ratio: float = 1.0

    def __post_init__(self):
        check_options(self, positive=("skin_modulus_kpa", "skin_thickness_mm", "dermal_modulus_kpa",
                                      "hypodermal_modulus_kpa", "anchor_modulus_kpa", "dermal_depth",
                                      "hypodermal_depth", "stiffening", "density_g_mm3"),
                      non_negative=("knee_strain", "damping_ratio", "drag", "flexion", "contact_margin_mm",
                                    "contact_stiffness", "bulk_ratio"))
        if not 0 < self.dermal_depth < self.hypodermal_depth < 1:
            raise ValueError("SkinMaterial: need 0 < dermal_depth < hypodermal_depth < 1, got "
                             f"{self.dermal_depth} and {self.hypodermal_depth}")
        if self.stiffening < 1:
            raise ValueError(f"SkinMaterial.stiffening must be >= 1, got {self.stiffening}")


@dataclass(frozen=True, eq=False)
class SkinLayers:
    """The particles of a head's skin and the system arrays built on them.

    Attributes
    ----------
    rest : (3n, 3) ndarray
        Rest positions, layer by layer (epidermis, dermis, hypodermis).
    vertices : int
        n, the head's vertex count.
    arrays : SkinArrays
        The validated system (springs, anchors, muscles, skull, jaw).
    muscle_names : tuple of str
        The muscles, in the order of ``arrays``' muscle rows.
    """

    rest: np.ndarray
    vertices: int
    arrays: SkinArrays
    muscle_names: tuple

    def layer(self, positions: np.ndarray, index: int) -> np.ndarray:
        """Rows of one layer (0 epidermis, 1 dermis, 2 hypodermis) of (3n, 3) positions."""
        return positions[index * self.vertices:(index + 1) * self.vertices]


def _edges(faces: np.ndarray) -> np.ndarray:
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def _edge_areas(vertices, faces, edges):
    """A third of the area of the triangles on each side of every edge (mm^2)."""
    area = 0.5 * np.linalg.norm(np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                                         vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1)
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    pairs = np.sort(pairs, axis=1)
    keys = pairs[:, 0] * (len(vertices) + 1) + pairs[:, 1]
    edge_keys = edges[:, 0] * (len(vertices) + 1) + edges[:, 1]
    order = np.argsort(edge_keys)
    position = order[np.searchsorted(edge_keys[order], keys)]
    out = np.zeros(len(edges))
    np.add.at(out, position, np.tile(area, 3) / 3.0)
    return out


def _flexion_pairs(faces: np.ndarray, n: int):
    """For every edge shared by two triangles: the two vertices opposite it (k, 2), and
    the edge (k, 2)."""
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    opposite = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    key = np.sort(pairs, axis=1)
    code = key[:, 0] * (n + 1) + key[:, 1]
    order = np.argsort(code, kind="stable")
    code, opposite, key = code[order], opposite[order], key[order]
    shared = np.flatnonzero(code[1:] == code[:-1])
    return np.stack([opposite[shared], opposite[shared + 1]], axis=1), key[shared]


def _two_ring_faces(faces: np.ndarray, n: int, indptr: np.ndarray, neighbours: np.ndarray):
    """CSR list, per vertex, of the triangles touching it or its neighbours, sorted."""
    incidence = sp.csr_matrix((np.ones(faces.size), (np.repeat(np.arange(len(faces)), 3), faces.reshape(-1))),
                              shape=(len(faces), n))
    adjacency = sp.csr_matrix((np.ones(len(neighbours)), neighbours, indptr), shape=(n, n))
    near = (adjacency + sp.identity(n, format="csr")) @ incidence.T  # vertex -> faces within one ring
    near = near.tocsr()
    near.sort_indices()
    return near.indptr.astype(np.int64), near.indices.astype(np.int64)


def _adjacency(n: int, edges: np.ndarray):
    """CSR vertex adjacency (indptr, neighbours), neighbours sorted."""
    both = np.concatenate([edges, edges[:, ::-1]])
    order = np.lexsort((both[:, 1], both[:, 0]))
    both = both[order]
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.add.at(indptr, both[:, 0] + 1, 1)
    return np.cumsum(indptr), both[:, 1].astype(np.int64)


def build_layers(head, material: SkinMaterial = SkinMaterial()) -> SkinLayers:
    """The three-layer particle system of a head (see the module notes)."""
    n = len(head.vertices)
    columns = _columns(head, material)
    first, second, stiffness = _springs(head, columns, material)
    rest_length = np.linalg.norm(columns.rest[second] - columns.rest[first], axis=1)
    masses = columns.masses
    reduced_mass = masses[first] * masses[second] / (masses[first] + masses[second])
    damping = 2.0 * material.damping_ratio * np.sqrt(stiffness * reduced_mass)

    anchor_particle = 2 * n + np.arange(n)
    anchor_stiffness = KPA * material.anchor_modulus_kpa * columns.area / columns.anchor_t
    anchor_damping = 2.0 * material.damping_ratio * np.sqrt(anchor_stiffness * masses[anchor_particle])
    bones = np.where(head.mandible, MANDIBLE, SKULL).astype(np.int64)
    hypodermis = columns.rest[2 * n:]

    lips = head.region_mask([r for r in ("upper_lip", "lower_lip") if r in head.region_names])
    own = np.zeros(3 * n)
    np.add.at(own, first, stiffness)
    np.add.at(own, second, stiffness)
    np.add.at(own, anchor_particle, anchor_stiffness)
    arrays = SkinArrays(
        masses=masses, spring_first=first, spring_second=second, spring_rest=rest_length,
        spring_stiffness=stiffness, spring_stiffness_high=stiffness * material.stiffening,
        spring_knee=np.full(len(first), material.knee_strain), spring_damping=damping,
        anchor_particle=anchor_particle, anchor_target=hypodermis.copy(), anchor_bone=bones,
        anchor_stiffness=anchor_stiffness, anchor_damping=anchor_damping, drag=material.drag,
        **_muscle_arrays(head, hypodermis),
        **_skull_arrays(head, columns.edges, bones),
        # Only the hypodermal layer meets the skull: it lies on it, and the layers above
        # reach it only through an inverted column, which the simulation refuses. (A
        # skin particle ~2 cm over the skull under the nose is also where a nearest-vertex
        # search can settle on the far side of a bump and call it inside.) The lips rest
        # on the teeth, which the model does not have, not on bone: their free margins
        # slide about the cut as the jaw opens, and meeting the cut's edge there made
        # them chatter.
        particle_foot=np.concatenate([np.full(2 * n, -1), np.where(lips, -1, np.arange(n))]),
        contact_stiffness=material.contact_stiffness * own,
        contact_damping=2.0 * material.damping_ratio * np.sqrt(material.contact_stiffness * own * masses),
        contact_margin=material.contact_margin_mm,
        jaw_pivot=head.jaw_pivot, jaw_axis=head.jaw_axis,
        **_prism_arrays(head, columns.rest, material),
    )
    arrays = _with_contact_margins(arrays, columns.rest, material)
    return SkinLayers(rest=columns.rest, vertices=n, arrays=arrays, muscle_names=head.muscle_names)


@dataclass(frozen=True)
class _Columns:
    """The layers' particles at rest along each skin vertex's column to its skull
    vertex, with what the springs and masses are made of."""

    rest: np.ndarray       # (3n, 3): epidermis, dermis, hypodermis
    edges: np.ndarray      # (e, 2) the skin's edges
    area: np.ndarray       # (n,) each vertex's Voronoi area
    dermal_t: np.ndarray   # (n,) thicknesses of the layers (mm)
    hypo_t: np.ndarray
    anchor_t: np.ndarray
    masses: np.ndarray     # (3n,)


def _columns(head, material: SkinMaterial) -> _Columns:
    skin, skull = head.vertices, head.skull_vertices
    depth = np.linalg.norm(skull - skin, axis=1)
    if np.any(depth <= 0.1):
        bad = np.flatnonzero(depth <= 0.1)[0]
        raise ValueError(f"head: skin vertex {bad} lies on its skull vertex (depth {depth[bad]:.3g} mm); "
                         "the skull must lie under the skin")
    toward = (skull - skin) / depth[:, None]
    fractions = (0.0, material.dermal_depth, material.hypodermal_depth)
    rest = np.concatenate([skin + f * depth[:, None] * toward for f in fractions])
    area = voronoi_areas(skin, head.faces)
    area = np.maximum(area, 1e-6 * max(area.max(), 1e-12))
    dermal_t = material.dermal_depth * depth
    hypo_t = (material.hypodermal_depth - material.dermal_depth) * depth
    anchor_t = (1.0 - material.hypodermal_depth) * depth
    rho = material.density_g_mm3
    masses = np.concatenate([rho * area * (material.skin_thickness_mm + 0.5 * dermal_t),
                             rho * area * 0.5 * (dermal_t + hypo_t),
                             rho * area * (0.5 * hypo_t + anchor_t)])
    return _Columns(rest, _edges(head.faces), area, dermal_t, hypo_t, anchor_t, masses)


def _springs(head, columns: _Columns, material: SkinMaterial):
    """Every spring (first, second particle, stiffness): each layer's membrane along the
    skin's edges, flexion across them, and columns and shear between the layers."""
    n = len(head.vertices)
    skin, faces, edges, rest = head.vertices, head.faces, columns.edges, columns.rest
    dermal_t, hypo_t, area = columns.dermal_t, columns.hypo_t, columns.area
    first, second, stiffness = [], [], []
    edge_area = _edge_areas(skin, faces, edges)
    a, b = edges[:, 0], edges[:, 1]
    length0 = np.linalg.norm(skin[b] - skin[a], axis=1)
    membrane = (
        material.skin_modulus_kpa * material.skin_thickness_mm + material.dermal_modulus_kpa * 0.5 * 0.5
        * (dermal_t[a] + dermal_t[b]),
        0.5 * 0.5 * (material.dermal_modulus_kpa * (dermal_t[a] + dermal_t[b])
                     + material.hypodermal_modulus_kpa * (hypo_t[a] + hypo_t[b])),
        0.5 * 0.5 * material.hypodermal_modulus_kpa * (hypo_t[a] + hypo_t[b]),
    )
    for layer, modulus_thickness in enumerate(membrane):
        # measured on the skin: the inner layers' edges are shorter by about depth / 10 cm
        first.append(layer * n + a)
        second.append(layer * n + b)
        stiffness.append(KPA * modulus_thickness * edge_area / np.maximum(length0, 1e-9) ** 2)
    # Flexion springs across every interior edge of the skin (between the two vertices
    # opposite it): a spring membrane has no bending stiffness, and under compression
    # it would fold at the mesh's scale. Each stands for the skin over its two
    # triangles bent about the edge, a fraction flexion of the membrane.
    flexion, hinge = _flexion_pairs(faces, n)
    if len(flexion):
        span = np.linalg.norm(skin[flexion[:, 1]] - skin[flexion[:, 0]], axis=1)
        edge_code = edges[:, 0] * (n + 1) + edges[:, 1]
        hinge_area = 3.0 * edge_area[np.searchsorted(edge_code, hinge[:, 0] * (n + 1) + hinge[:, 1])]
        first.append(flexion[:, 0])
        second.append(flexion[:, 1])
        stiffness.append(KPA * material.flexion * material.skin_modulus_kpa * material.skin_thickness_mm
                         * hinge_area / np.maximum(span, 1e-9) ** 2)
    # between layers: a column spring per vertex and shear springs along the edges
    degree = np.bincount(edges.reshape(-1), minlength=n).astype(np.float64)
    for slab, (modulus, thickness) in enumerate(((material.dermal_modulus_kpa, dermal_t),
                                                 (material.hypodermal_modulus_kpa, hypo_t))):
        top, bottom = slab * n, (slab + 1) * n
        first.append(top + np.arange(n))
        second.append(bottom + np.arange(n))
        stiffness.append(KPA * modulus * area / thickness)
        # Shear: a tangential shift u of the top over the bottom meets G A / t per
        # column; a cross spring of length c over an edge of length l gives (l / c)^2 of
        # its stiffness against it, averaged over directions (1/2); each column has
        # 2 * degree such springs, each shared by the two columns at its ends.
        shear = modulus / 3.0
        for upper, lower in ((a, b), (b, a)):
            cross = np.linalg.norm(rest[bottom + lower] - rest[top + upper], axis=1)
            column_t = 0.5 * (thickness[upper] + thickness[lower])
            column_a = 0.5 * (area[upper] + area[lower])
            per_column = 0.5 * (degree[upper] + degree[lower])
            k = KPA * shear * column_a / column_t * 2.0 * cross**2 / (np.maximum(length0, 1e-9) ** 2 * per_column)
            first.append(top + upper)
            second.append(bottom + lower)
            stiffness.append(k)
    return (np.concatenate(first).astype(np.int64), np.concatenate(second).astype(np.int64),
            np.concatenate(stiffness))


def _prism_arrays(head, rest: np.ndarray, material: SkinMaterial) -> dict:
    """The prisms' fields of SkinArrays: each skin triangle over the same triangle one
    layer down, in both slabs, with k = K / V0 (K the slab's bulk modulus); none when
    ``bulk_ratio`` is 0."""
    n, faces = len(head.vertices), np.asarray(head.faces, dtype=np.int64)
    if material.bulk_ratio == 0 or len(faces) == 0:
        return dict(prism_particles=np.zeros((0, 6), dtype=np.int64), prism_rest_volume=np.zeros(0),
                    prism_stiffness=np.zeros(0))
    particles, stiffness = [], []
    for slab, modulus in enumerate((material.dermal_modulus_kpa, material.hypodermal_modulus_kpa)):
        particles.append(np.concatenate([slab * n + faces, (slab + 1) * n + faces], axis=1))
        stiffness.append(np.full(len(faces), KPA * material.bulk_ratio * modulus))
    particles = np.concatenate(particles)
    stiffness = np.concatenate(stiffness)
    # The skin's triangles face out and the layers lie below, which makes the tetrahedra
    # (a b c A ...) negative: the prism read from below is positive.
    particles, volume = oriented_prisms(particles, rest)
    # a prism flattened at rest (a column of no depth) keeps nothing
    keep = volume > 1e-9 * max(volume.max(initial=0.0), 1e-300)
    return dict(prism_particles=particles[keep], prism_rest_volume=volume[keep],
                prism_stiffness=stiffness[keep] / volume[keep])


def _muscle_arrays(head, hypodermis: np.ndarray) -> dict:
    """The muscles' fields of SkinArrays: each muscle's weights over the hypodermal
    particles of its regions."""
    n = len(head.vertices)
    kinds, muscle_bones, points, axes, forces = [], [], [], [], []
    indptr, particles, weights = [0], [], []
    for muscle in head.muscles:
        allowed = head.region_mask(muscle.regions)
        if isinstance(muscle, SkinLinearMuscle):
            attachment = muscle.attachment.position(head.skull_vertices, head.faces)
            insertion = muscle.insertion.position(hypodermis, head.faces)
            index, weight = muscle_weights(muscle, hypodermis, allowed, attachment=attachment, insertion=insertion)
            kinds.append(LINEAR)
            points.append(attachment)
            axes.append(np.zeros(6))
        else:
            index, weight = muscle_weights(muscle, hypodermis, allowed)
            kinds.append(SPHINCTER)
            points.append(muscle.epicentre)
            unit = muscle.axes / np.linalg.norm(muscle.axes, axis=1, keepdims=True)
            axes.append(unit.reshape(-1))
        muscle_bones.append(MANDIBLE if muscle.bone == "mandible" else SKULL)
        forces.append(muscle.max_force_n * NEWTON)
        particles.append(2 * n + index)
        weights.append(weight)
        indptr.append(indptr[-1] + len(index))
    return dict(
        muscle_kind=np.array(kinds, dtype=np.int64), muscle_bone=np.array(muscle_bones, dtype=np.int64),
        muscle_point=np.array(points, dtype=np.float64).reshape(-1, 3),
        muscle_axes=np.array(axes, dtype=np.float64).reshape(-1, 6),
        muscle_max_force=np.array(forces, dtype=np.float64),
        muscle_indptr=np.array(indptr, dtype=np.int64),
        muscle_particles=np.concatenate(particles).astype(np.int64) if particles else np.zeros(0, dtype=np.int64),
        muscle_weights=np.concatenate(weights) if weights else np.zeros(0))


def _skull_arrays(head, edges: np.ndarray, bones: np.ndarray) -> dict:
    """The skull's fields of SkinArrays: its surface (the skin's triangles over the
    skull vertices), normals, rim and the adjacency the contact search walks."""
    n, skull, faces = len(head.vertices), head.skull_vertices, head.faces
    indptr_skull, neighbours = _adjacency(n, edges)
    face_indptr, vertex_faces = _two_ring_faces(faces, n, indptr_skull, neighbours)
    return dict(skull_vertices=skull, skull_normals=vertex_normals(skull, faces), skull_faces=faces,
                skull_face_indptr=face_indptr, skull_vertex_faces=vertex_faces,
                skull_face_rim=rim_edges(faces, n, bones), skull_bone=bones,
                skull_indptr=indptr_skull, skull_neighbours=neighbours)


def _with_contact_margins(arrays: SkinArrays, rest: np.ndarray, material: SkinMaterial) -> SkinArrays:
    """The arrays with each particle's contact foot and margin at rest.

    The penalty must not push any particle at rest: where a particle rests closer to
    the skull than the margin (thin tissue, or a skull surface oblique to the column),
    its zone starts at half its rest height. Heights are taken from each particle's
    nearest skull vertex, where the contact search starts (a column's own skull vertex
    is not always the nearest: the rays toward the head's centre are oblique to the
    skull at the sides): a compiled system of the arrays so far walks each foot there
    and measures the heights.
    """
    checked = arrays.validated()
    system = checked.core()
    foot = system.project_contacts(rest, np.zeros_like(rest), checked.particle_foot, 0.0)[2]
    height = system.skull_heights(rest, foot, 0.0)
    margin = np.clip(np.minimum(material.contact_margin_mm, 0.5 * height), 0.0, None)
    return replace(arrays, particle_foot=foot, contact_margin=margin).validated()

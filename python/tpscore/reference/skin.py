"""NumPy reference for the layered skin simulation (``tpscore/skin_sim.hpp``).

The same model and the same step, vectorised over springs, anchors and muscle
entries and scattered to particles with ``np.add.at``; the implicit step assembles
(M + dt D + dt^2 K) with scipy.sparse and solves it with ``spsolve``. ``arrays`` is a
:class:`tpscore.physics.system.SkinArrays` (or anything with the same attributes).
Sums run in a different order than in the compiled core, so results agree to
rounding, not bit for bit.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..physics.linearised import (prism_stiffness_matrix, prism_volumes, spring_damping_matrix, spring_state,
                                  spring_stiffness_matrix)
from .spatial import closest_point_on_triangles

__all__ = [
    "SKULL",
    "MANDIBLE",
    "LINEAR",
    "SPHINCTER",
    "jaw_rotation",
    "bone_points",
    "spring_state",
    "forces",
    "potential_energy",
    "kinetic_energy",
    "project_contacts",
    "stiffness_matrix",
    "damping_matrix",
    "free_forces",
    "locate",
    "step",
    "run",
]

SKULL, MANDIBLE = 0, 1
LINEAR, SPHINCTER = 0, 1
#: Length (mm) over which a muscle's pull fades to zero at its attachment.
MUSCLE_CORE = 1.0
#: The contact direction blends triangles up to this fraction of the largest contact
#: margin farther than the closest one.
CONTACT_BLEND = 0.5
#: Width of the rounded lip the skull's rim ends in, in largest contact margins.
RIM_ROUNDING = 8.0


def jaw_rotation(axis, angle: float) -> np.ndarray:
    """Rotation matrix (3, 3) by `angle` radians about the unit `axis` (Rodrigues)."""
    k = np.asarray(axis, dtype=np.float64)
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.cos(angle) * np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * np.outer(k, k)


def bone_points(arrays, points, bones, angle: float) -> np.ndarray:
    """Points fixed to bones, with the mandible's rotated by the jaw angle."""
    points = np.array(points, dtype=np.float64, copy=True)
    on_jaw = np.asarray(bones) == MANDIBLE
    if on_jaw.any():
        rotation = jaw_rotation(arrays.jaw_axis, angle)
        points[on_jaw] = arrays.jaw_pivot + (points[on_jaw] - arrays.jaw_pivot) @ rotation.T
    return points


def _skull_at(arrays, jaw_angle):
    """Skull vertices, vertex normals and triangle normals at a jaw angle."""
    skull = bone_points(arrays, arrays.skull_vertices, arrays.skull_bone, jaw_angle)
    normals = arrays.skull_normals.copy()
    on_jaw = arrays.skull_bone == MANDIBLE
    normals[on_jaw] = normals[on_jaw] @ jaw_rotation(arrays.jaw_axis, jaw_angle).T
    faces = arrays.skull_faces
    cross = np.cross(skull[faces[:, 1]] - skull[faces[:, 0]], skull[faces[:, 2]] - skull[faces[:, 0]])
    length = np.linalg.norm(cross, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        face_normals = np.where(length[:, None] > 0, cross / length[:, None], 0.0)
    return skull, normals, face_normals


def locate(arrays, points, foot, jaw_angle: float = 0.0, geometry=None):
    """Where points meet the skull: (height (m,), normal (m, 3), closest point (m, 3)).

    The closest point of the triangles listed near each point's skull vertex `foot` that
    lie wholly on that vertex's bone, the distance to it signed by the triangle's
    normal, and the unit direction out of the skull, blended over the triangles up to
    CONTACT_BLEND times the largest margin farther (weights (1 - excess / blend)^2); the
    vertex's tangent plane where no such triangle exists. Where the closest point lies
    on the skull's rim, the bone ends in a rounded lip RIM_ROUNDING margins wide that
    curves back behind the rim by as much (:func:`_lip`; beyond it the particle is beside
    the bone, at its distance from the rim), and height and direction are averaged over
    the nearly-as-close rim triangles, the direction handed over from the blended one
    within the blend's width of the edge.
    """
    skull, normals, face_normals = _skull_at(arrays, jaw_angle) if geometry is None else geometry
    points = np.asarray(points, dtype=np.float64)
    foot = np.asarray(foot, dtype=np.int64)
    start, stop = arrays.skull_face_indptr[foot], arrays.skull_face_indptr[foot + 1]
    bone = arrays.skull_bone[foot]
    best = np.full(len(points), np.inf)
    best_point = np.zeros_like(points)
    best_face = np.full(len(points), -1)
    best_rim = np.zeros(len(points), dtype=bool)
    best_bary = np.zeros_like(points)
    # every listed triangle wholly on the bone with the closest point on it, found once:
    # the closest gives the height, the nearly-as-close ones the direction
    hits = []
    for offset in range(int((stop - start).max(initial=0))):
        has = start + offset < stop
        face = np.where(has, arrays.skull_vertex_faces[np.minimum(start + offset, len(arrays.skull_vertex_faces) - 1)],
                        0)
        corners = arrays.skull_faces[face]
        has &= np.all(arrays.skull_bone[corners] == bone[:, None], axis=1)
        closest, bary, d2 = closest_point_on_triangles(points, skull[corners[:, 0]], skull[corners[:, 1]],
                                                      skull[corners[:, 2]])
        rim_bits = arrays.skull_face_rim[face]
        on_rim = np.zeros(len(points), dtype=bool)
        for k in range(3):
            on_rim |= (bary[:, k] == 0.0) & (((rim_bits >> k) & 1) == 1)
        hits.append((has, face, closest, d2, on_rim, bary))
        better = has & (d2 < best)  # strict: the first triangle wins a tie, as in the core
        best_rim = np.where(better, on_rim, best_rim)
        best_bary = np.where(better[:, None], bary, best_bary)
        best = np.where(better, d2, best)
        best_point = np.where(better[:, None], closest, best_point)
        best_face = np.where(better, face, best_face)
    found = best_face >= 0
    offset = points - best_point
    distance = np.sqrt(np.where(found, best, 0.0))
    face_normal = face_normals[np.maximum(best_face, 0)]
    side = np.where(np.einsum("ij,ij->i", offset, face_normal) >= 0, 1.0, -1.0)
    height = side * distance
    # the direction out of the skull, blended over the nearly-as-close triangles the
    # particle lies in front of or beside (see the core's blended_direction); inside, the
    # closest triangle's
    blend = CONTACT_BLEND * max(float(np.max(arrays.contact_margin, initial=0.0)), 0.0)
    direction_sum = np.zeros_like(points)
    for has, face, closest, d2, on_rim, _ in hits:
        own = np.sqrt(d2)
        excess = own - distance
        is_best = face == best_face
        to_point = points - closest
        # a triangle the particle lies behind (and not beside its rim) has no say
        has = (has & found & (is_best | (excess < blend)) & (own > 1e-12)
               & (is_best | on_rim | (np.einsum("ij,ij->i", to_point, face_normals[face]) >= 0)))
        with np.errstate(invalid="ignore", divide="ignore"):
            term = (_closeness_weight(is_best, excess, blend) / own)[:, None] * to_point
        direction_sum += np.where(has[:, None], term, 0.0)
    length = np.linalg.norm(direction_sum, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        normal = np.where(((distance > 1e-12) & (length > 1e-12))[:, None], direction_sum / length[:, None],
                          face_normal)
        # inside the skull (not beside its rim): straight back out of the closest triangle
        inside_normal = np.where((distance > 1e-12)[:, None], -offset / distance[:, None], face_normal)
    inside = (side < 0) & ~best_rim
    normal = np.where(inside[:, None], inside_normal, normal)
    plane_normal = normals[foot]
    plane_height = np.einsum("ij,ij->i", points - skull[foot], plane_normal)
    # beside the rim of the bone: outside, at the distance from the rim
    height = np.where(found, np.where(best_rim, distance, height), plane_height)
    normal = np.where(found[:, None], normal, plane_normal)
    point = np.where(found[:, None], best_point, points - plane_height[:, None] * plane_normal)
    # where the closest point lies on the rim (see _rim_contacts)
    rim = found & best_rim
    if rim.any():
        edge = np.where((side < 0)[:, None], face_normal, normal)
        height[rim], normal[rim] = _rim_contacts(arrays, normals, face_normals, points, hits, best_face, distance,
                                                 blend, edge, rim)
        point[rim] = points[rim] - height[rim][:, None] * normal[rim]
    return height, normal, point


def _rim_contacts(arrays, normals, face_normals, points, hits, best_face, distance, blend, edge, rim):
    """Height and direction of the points `rim` whose closest point lies on the rim:
    averaged over the nearly-as-close rim triangles, each with its lip's (:func:`_lip`),
    the direction handed over within the blend's width of the edge from `edge` (the
    one just over the triangle: blended in front, straight out from behind); see the
    core's rim_contact."""
    rounding = RIM_ROUNDING * max(float(np.max(arrays.contact_margin, initial=0.0)), 0.0)
    height_sum = np.zeros(len(points))
    weight_sum = np.zeros(len(points))
    rim_sum = np.zeros_like(points)
    across = np.zeros(len(points))
    for has, face, closest, d2, on_rim, bary in hits:
        own = np.sqrt(d2)
        excess = own - distance
        is_best = face == best_face
        use = rim & has & on_rim & (is_best | (excess < blend))
        weight = _closeness_weight(is_best, excess, blend)
        with np.errstate(invalid="ignore", divide="ignore"):
            direction = np.where((own > 1e-12)[:, None], (points - closest) / own[:, None], face_normals[face])
        lip, lip_height, lip_direction, hit_across = _lip(arrays, normals, face_normals, points, closest, bary, face,
                                                          on_rim, rounding)
        across = np.where(use & is_best, hit_across, across)
        height_sum += np.where(use, weight * np.where(lip, lip_height, own), 0.0)
        weight_sum += np.where(use, weight, 0.0)
        rim_sum += np.where(use[:, None], weight[:, None] * np.where(lip[:, None], lip_direction, direction), 0.0)
    length = np.linalg.norm(rim_sum[rim], axis=1)
    rim_normal = np.where((length > 1e-12)[:, None], rim_sum[rim] / np.maximum(length, 1e-300)[:, None],
                          face_normals[best_face[rim]])
    t = np.minimum(across[rim] / blend, 1.0) if blend > 0 else np.ones(int(rim.sum()))
    handover = (t * t * (3.0 - 2.0 * t))[:, None]
    turned = (1.0 - handover) * edge[rim] + handover * rim_normal
    turned /= np.linalg.norm(turned, axis=1)[:, None]
    return height_sum[rim] / weight_sum[rim], np.where((t < 1.0)[:, None], turned, rim_normal)


def _closeness_weight(is_best, excess, blend):
    """Weights of the blends over the nearly-as-close triangles: 1 for the closest,
    (1 - excess / blend)^2 within `blend` farther (callers mask the rest out)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(is_best, 1.0, (1.0 - excess / blend) ** 2 if blend > 0 else 0.0)


def _lip(arrays, normals, face_normals, points, closest, bary, face, on_rim, rounding):
    """The rim's rounded lip seen from each point whose closest point on triangle
    `face` is `closest` (weights `bary`, on a rim edge where `on_rim`): (within the lip
    (m,), height (m,), unit direction (m, 3), distance across the edge (m,)); see the
    core's lip_contact."""
    face_normal = face_normals[face]
    offset = points - closest
    beyond = offset - np.einsum("ij,ij->i", offset, face_normal)[:, None] * face_normal
    across = np.linalg.norm(beyond, axis=1)
    inside = on_rim & (across < rounding)
    s = np.where(inside, across / rounding, 0.0)[:, None] if rounding > 0 else np.zeros((len(points), 1))
    curve = s * s * (3.0 - 2.0 * s)
    rise = 6.0 * s * (1.0 - s)
    with np.errstate(invalid="ignore", divide="ignore"):
        outward = np.where((across > 1e-12)[:, None], beyond / across[:, None], 0.0)
        rim_normal = np.einsum("ik,ikj->ij", bary, normals[arrays.skull_faces[face]])
        rim_normal /= np.linalg.norm(rim_normal, axis=1)[:, None]
        normal = (1.0 - curve) * face_normal + curve * rim_normal
        normal /= np.linalg.norm(normal, axis=1)[:, None]
        gradient = normal + rise * outward
        slope = np.linalg.norm(gradient, axis=1)
        height = (np.einsum("ij,ij->i", offset, normal) + rounding * curve[:, 0]) / slope
        direction = gradient / slope[:, None]
    return inside, np.where(inside, height, 0.0), np.where(inside[:, None], direction, 0.0), across


def forces(arrays, positions, velocities, contractions, jaw_angle: float, foot=None) -> np.ndarray:
    """Net force (n, 3) on every particle; with `foot` (each particle's nearest skull
    vertex) the contact penalty too."""
    positions = np.asarray(positions, dtype=np.float64)
    velocities = np.asarray(velocities, dtype=np.float64)
    n = len(arrays.masses)
    total = -arrays.drag * arrays.masses[:, None] * velocities
    direction, _, force, _ = spring_state(arrays, positions)
    relative = velocities[arrays.spring_second] - velocities[arrays.spring_first]
    along = force + arrays.spring_damping * np.einsum("ij,ij->i", direction, relative)
    pull = along[:, None] * direction
    np.add.at(total, arrays.spring_first, pull)
    np.add.at(total, arrays.spring_second, -pull)

    volume, gradient = prism_volumes(arrays, positions)
    pressure = -arrays.prism_stiffness * (volume - arrays.prism_rest_volume)
    np.add.at(total, arrays.prism_particles.reshape(-1), (pressure[:, None, None] * gradient).reshape(-1, 3))

    targets = bone_points(arrays, arrays.anchor_target, arrays.anchor_bone, jaw_angle)
    p = arrays.anchor_particle
    np.add.at(total, p, arrays.anchor_stiffness[:, None] * (targets - positions[p])
              - arrays.anchor_damping[:, None] * velocities[p])

    contractions = np.asarray(contractions, dtype=np.float64)
    if len(arrays.muscle_kind):
        points = bone_points(arrays, arrays.muscle_point, arrays.muscle_bone, jaw_angle)
        counts = np.diff(arrays.muscle_indptr)
        muscle = np.repeat(np.arange(len(arrays.muscle_kind)), counts)
        particle = arrays.muscle_particles
        toward = points[muscle] - positions[particle]
        sphincter = arrays.muscle_kind[muscle] == SPHINCTER
        a = arrays.muscle_axes[muscle, :3]
        b = arrays.muscle_axes[muscle, 3:]
        in_plane = (np.einsum("ij,ij->i", a, toward)[:, None] * a
                    + np.einsum("ij,ij->i", b, toward)[:, None] * b)
        toward = np.where(sphincter[:, None], in_plane, toward)
        length = np.linalg.norm(toward, axis=1)
        magnitude = contractions[muscle] * arrays.muscle_max_force[muscle] * arrays.muscle_weights
        # the pull fades to zero within MUSCLE_CORE of the attachment (see the core)
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where((length > 0) & (magnitude != 0), magnitude / np.maximum(length, MUSCLE_CORE), 0.0)
        np.add.at(total, particle, scale[:, None] * toward)
    if foot is not None and len(arrays.skull_vertices):
        foot = np.asarray(foot)
        rows = np.flatnonzero((foot >= 0) & (arrays.contact_stiffness > 0))
        height, normal, _ = locate(arrays, positions[rows], foot[rows], jaw_angle)
        inside = height < arrays.contact_margin[rows]
        r = rows[inside]
        push = (arrays.contact_stiffness[r] * (arrays.contact_margin[r] - height[inside])
                - arrays.contact_damping[r] * np.einsum("ij,ij->i", velocities[r], normal[inside]))
        total[r] += push[:, None] * normal[inside]
    assert total.shape == (n, 3)
    return total


def potential_energy(arrays, positions, jaw_angle: float = 0.0) -> float:
    """Elastic energy of the springs (biphasic law integrated), the anchors and the prisms."""
    _, length, _, _ = spring_state(arrays, positions)
    extension = np.abs(length - arrays.spring_rest)
    limit = arrays.spring_knee * arrays.spring_rest
    beyond = np.maximum(extension - limit, 0.0)
    below = np.minimum(extension, limit)
    springs = (0.5 * arrays.spring_stiffness * below ** 2 + arrays.spring_stiffness * limit * beyond
               + 0.5 * arrays.spring_stiffness_high * beyond ** 2)
    targets = bone_points(arrays, arrays.anchor_target, arrays.anchor_bone, jaw_angle)
    anchors = 0.5 * arrays.anchor_stiffness * np.sum((positions[arrays.anchor_particle] - targets) ** 2, axis=1)
    volume, _ = prism_volumes(arrays, positions)
    prisms = 0.5 * arrays.prism_stiffness * (volume - arrays.prism_rest_volume) ** 2
    return float(springs.sum() + anchors.sum() + prisms.sum())


def kinetic_energy(arrays, velocities) -> float:
    return float(0.5 * np.sum(arrays.masses[:, None] * np.asarray(velocities) ** 2))


def project_contacts(arrays, positions, velocities, foot, jaw_angle: float):
    """Skull contact: walk each particle's skull vertex downhill to the nearest one, and
    move a particle below that vertex's tangent plane back onto it."""
    positions = np.array(positions, dtype=np.float64, copy=True)
    velocities = np.array(velocities, dtype=np.float64, copy=True)
    foot = np.array(foot, dtype=np.int64, copy=True)
    if len(arrays.skull_vertices) == 0:
        return positions, velocities, foot
    skull, _, _ = _skull_at(arrays, jaw_angle)
    active = np.flatnonzero(foot >= 0)
    indptr, neighbours = arrays.skull_indptr, arrays.skull_neighbours
    walking = active.copy()
    # the walk stays on each particle's own bone (see the core)
    bone_of = arrays.skull_bone[foot]
    best = np.sum((skull[foot[walking]] - positions[walking]) ** 2, axis=1)
    for _ in range(64):
        if walking.size == 0:
            break
        moved = np.zeros(len(walking), dtype=bool)
        # the neighbours in stored order, a strict improvement each, as the core does
        start, stop = indptr[foot[walking]], indptr[foot[walking] + 1]
        current = foot[walking].copy()
        bone = bone_of[walking]
        for offset in range(int((stop - start).max(initial=0))):
            has = start + offset < stop
            candidate = np.where(has, neighbours[np.minimum(start + offset, len(neighbours) - 1)], -1)
            has &= arrays.skull_bone[np.maximum(candidate, 0)] == bone
            distance = np.where(has, np.sum((skull[np.maximum(candidate, 0)] - positions[walking]) ** 2, axis=1),
                                np.inf)
            better = distance < best
            best = np.where(better, distance, best)
            current = np.where(better, candidate, current)
            moved |= better
        foot[walking] = current
        walking, best = walking[moved], best[moved]
    height, normal, point = locate(arrays, positions[active], foot[active], jaw_angle)
    below = height < 0.0
    rows = active[below]
    positions[rows] = point[below]
    inward = np.einsum("ij,ij->i", velocities[rows], normal[below])
    velocities[rows] -= np.minimum(inward, 0.0)[:, None] * normal[below]
    return positions, velocities, foot


def stiffness_matrix(arrays, positions, *, tension_only: bool = True, foot=None,
                     jaw_angle: float = 0.0) -> sp.csr_matrix:
    """K = -df/dx of the springs, anchors, prisms and contact penalty at `positions`
    (3n, 3n); muscles left out (the implicit step treats them explicitly), the prisms'
    volume term by its Gauss-Newton part k g g^T, as the core does. With tension_only the
    geometric term of compressed springs is dropped, as the implicit step does; the
    penalty counts where a particle is within the contact margin of the skull around
    its skull vertex `foot` (nowhere without `foot`)."""
    n = len(arrays.masses)
    positions = np.asarray(positions, dtype=np.float64)
    matrix = spring_stiffness_matrix(arrays, positions, tension_only=tension_only)
    matrix = matrix + prism_stiffness_matrix(arrays, positions)
    rows, normal = _contact_rows(arrays, positions, foot, jaw_angle)
    if len(rows):
        matrix = matrix + _block_diagonal(n, rows, arrays.contact_stiffness[rows, None, None]
                                          * np.einsum("si,sj->sij", normal, normal))
    return matrix


def damping_matrix(arrays, positions, *, foot=None, jaw_angle: float = 0.0) -> sp.csr_matrix:
    """D = -df/dv at `positions` (3n, 3n): spring damping along each spring, anchor
    damping, drag, and the contact penalty's damping where the stiffness matrix counts
    the penalty."""
    n = len(arrays.masses)
    positions = np.asarray(positions, dtype=np.float64)
    matrix = spring_damping_matrix(arrays, positions)
    rows, normal = _contact_rows(arrays, positions, foot, jaw_angle)
    if len(rows):
        matrix = matrix + _block_diagonal(n, rows, arrays.contact_damping[rows, None, None]
                                          * np.einsum("si,sj->sij", normal, normal))
    return matrix


def _contact_rows(arrays, positions, foot, jaw_angle):
    """Particles within the contact margin of the skull, and their directions out of it."""
    if len(arrays.skull_vertices) == 0 or foot is None:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    foot = np.asarray(foot)
    rows = np.flatnonzero((foot >= 0) & (arrays.contact_stiffness > 0))
    height, normal, _ = locate(arrays, positions[rows], foot[rows], jaw_angle)
    inside = height < arrays.contact_margin[rows]
    return rows[inside], normal[inside]


def _block_diagonal(n, rows, blocks):
    r = np.arange(3)
    row_index = (3 * rows[:, None, None] + r[None, :, None]).repeat(3, axis=2).reshape(-1)
    col_index = (3 * rows[:, None, None] + r[None, None, :]).repeat(3, axis=1).reshape(-1)
    return sp.coo_matrix((blocks.reshape(-1), (row_index, col_index)), shape=(3 * n, 3 * n)).tocsr()


def step(arrays, positions, velocities, foot, contractions, jaw_angle: float, dt: float,
         integrator: str = "symplectic"):
    """One step: semi-implicit Euler or linearised backward Euler, then skull contact."""
    positions = np.asarray(positions, dtype=np.float64)
    velocities = np.asarray(velocities, dtype=np.float64)
    force = forces(arrays, positions, velocities, contractions, jaw_angle, foot)
    if integrator == "symplectic":
        velocities = velocities + dt * force / arrays.masses[:, None]
    elif integrator == "implicit":
        stiffness = stiffness_matrix(arrays, positions, foot=foot, jaw_angle=jaw_angle)
        damping = damping_matrix(arrays, positions, foot=foot, jaw_angle=jaw_angle)
        mass = sp.diags(np.repeat(arrays.masses, 3))
        system = (mass + dt * damping + dt * dt * stiffness).tocsc()
        rhs = dt * (force.reshape(-1) - dt * (stiffness @ velocities.reshape(-1)))
        velocities = velocities + spla.spsolve(system, rhs).reshape(-1, 3)
    else:
        raise ValueError(f"integrator must be 'symplectic' or 'implicit', got {integrator!r}")
    positions = positions + dt * velocities
    return project_contacts(arrays, positions, velocities, foot, jaw_angle)


def free_forces(arrays, positions, velocities, foot, contractions, jaw_angle: float) -> np.ndarray:
    """The net force less what the skull bears: the inward normal part of the force on a
    particle lying on the skull (put there by the projection) is removed."""
    force = forces(arrays, positions, velocities, contractions, jaw_angle, foot)
    if len(arrays.skull_vertices) == 0:
        return force
    foot = np.asarray(foot)
    rows = np.flatnonzero(foot >= 0)
    height, normal, _ = locate(arrays, positions[rows], foot[rows], jaw_angle)
    inward = np.einsum("ij,ij->i", force[rows], normal)
    touching = (height <= 1e-9) & (inward < 0)
    force[rows[touching]] -= inward[touching][:, None] * normal[touching]
    return force


def _smoothstep(s: float) -> float:
    s = min(max(s, 0.0), 1.0)
    return s * s * (3.0 - 2.0 * s)


def run(arrays, positions, velocities, foot, contractions, jaw_angle: float, *, integrator="symplectic",
        dt=1e-4, max_steps=10000, ramp_time=0.0, velocity_tolerance=0.5, force_tolerance=1e-3,
        patience=5, check_every=1, divergence_distance=200.0, record_every=0, record_count=0,
        rest_stiffness=None):
    """The core's run loop, step for step: ramp the controls (smoothstep) to their
    target, test for rest under the full controls, stop when settled or diverged.

    Returns (positions, velocities, foot, report dict, frame_times, frames).
    """
    positions = np.array(positions, dtype=np.float64, copy=True)
    velocities = np.array(velocities, dtype=np.float64, copy=True)
    foot = np.array(foot, dtype=np.int64, copy=True)
    contractions = np.asarray(contractions, dtype=np.float64)
    rest = positions.copy()
    if rest_stiffness is None:
        rest_stiffness = np.zeros(len(arrays.masses))
        np.add.at(rest_stiffness, arrays.spring_first, arrays.spring_stiffness)
        np.add.at(rest_stiffness, arrays.spring_second, arrays.spring_stiffness)
        np.add.at(rest_stiffness, arrays.anchor_particle, arrays.anchor_stiffness)
        rest_stiffness[~(rest_stiffness > 0)] = 1.0
    report = dict(steps=0, settled=False, diverged=False, time=0.0, max_speed=0.0, max_residual=0.0)
    times, frames = [], []

    def record(time):
        if record_count > 0:
            times.append(time)
            frames.append(positions[:record_count].copy())

    if record_every > 0:
        record(0.0)
    calm = 0
    last_recorded = 0
    for k in range(int(max_steps)):
        start = k * dt
        if start >= ramp_time and k % max(int(check_every), 1) == 0:
            force = free_forces(arrays, positions, velocities, foot, contractions, jaw_angle)
            speed = float(np.linalg.norm(velocities, axis=1).max())
            residual = float((np.linalg.norm(force, axis=1) / rest_stiffness).max())
            report.update(max_speed=speed, max_residual=residual)
            calm = calm + 1 if speed < velocity_tolerance and residual < force_tolerance else 0
            if calm >= patience:
                report["settled"] = True
                break
        s = _smoothstep((start + dt) / ramp_time) if ramp_time > 0 else 1.0
        positions, velocities, foot = step(arrays, positions, velocities, foot, s * contractions,
                                           s * jaw_angle, dt, integrator)
        report.update(steps=k + 1, time=(k + 1) * dt)
        far = np.linalg.norm(positions - rest, axis=1).max()
        if not (np.isfinite(positions).all() and np.isfinite(velocities).all()) or far > divergence_distance:
            report["diverged"] = True
            break
        if record_every > 0 and (k + 1) % record_every == 0:
            record((k + 1) * dt)
            last_recorded = k + 1
    if record_every > 0 and last_recorded != report["steps"] and not report["diverged"]:
        record(report["time"])
    frames = np.array(frames).reshape(-1, max(int(record_count), 0), 3) if frames else np.zeros((0, record_count, 3))
    return positions, velocities, foot, report, np.array(times), frames

"""Small heads and skin systems for the physical-skin tests, built by hand so that
their answers are known."""
from __future__ import annotations

import numpy as np

from tpscore.face.landmarks import N_LANDMARKS
from tpscore.physics import Head, SkinLinearMuscle, SkinSphincterMuscle, SurfacePoint
from tpscore.physics.linearised import oriented_prisms
from tpscore.physics.system import SkinArrays, rim_edges
from tpscore.spatial import MeshSurface


def flat_head(size: int = 9, spacing: float = 2.5, depth: float = 8.0, muscles=(), mandible_rows: int = 0) -> Head:
    """A flat square of skin (z = 0) over a flat skull (z = -depth), one region
    ("upper_face"), the bottom `mandible_rows` rows on the mandible, the jaw's pivot
    40 mm behind the middle of the top edge."""
    xs = (np.arange(size) - (size - 1) / 2) * spacing
    x, y = np.meshgrid(xs, -xs)
    vertices = np.column_stack([x.ravel(), y.ravel(), np.zeros(size * size)])
    index = np.arange(size * size).reshape(size, size)
    faces = []
    for r in range(size - 1):
        for c in range(size - 1):
            a, b, d, e = index[r, c], index[r, c + 1], index[r + 1, c], index[r + 1, c + 1]
            faces += [(a, d, b), (b, d, e)]
    skull = vertices - np.array([0.0, 0.0, depth])
    mandible = np.zeros(size * size, dtype=bool)
    if mandible_rows:
        mandible[index[-mandible_rows:].ravel()] = True
    return Head(vertices, np.array(faces), skull, np.full(N_LANDMARKS, -1), np.zeros(size * size, dtype=np.int64),
                ("upper_face",), mandible, np.array([0.0, xs.max(), -40.0]), np.array([1.0, 0.0, 0.0]),
                muscles=tuple(muscles))


def surface_point(head: Head, x: float, y: float) -> SurfacePoint:
    """The point of the head's (flat) mesh above (x, y)."""
    hits = MeshSurface(head.vertices, head.faces).intersect_rays([[x, y, 10.0]], [[0.0, 0.0, -1.0]])
    assert hits.hit[0]
    return SurfacePoint(int(hits.triangles[0]), tuple(hits.barycentric[0]))


def linear_muscle(head: Head, name="pull", attachment=(0.0, 8.0), insertion=(0.0, -2.0), force=0.5, **kw):
    return SkinLinearMuscle(name, surface_point(head, *attachment), surface_point(head, *insertion), ("upper_face",),
                        force, **kw)


def sphincter(name="ring", centre=(0.0, 0.0, 0.0), force=0.3):
    return SkinSphincterMuscle(name, np.array(centre), np.array([[6.0, 0.0, 0.0], [0.0, 4.0, 0.0]]), ("upper_face",),
                           force)


def random_arrays(seed: int = 0, n: int = 7) -> SkinArrays:
    """A random chain-and-cross system with anchors on both bones, a linear and a
    sphincter muscle, biphasic springs and a flat skull under it (for core vs reference)."""
    rng = np.random.default_rng(seed)
    positions = np.column_stack([rng.uniform(-4, 4, n), rng.uniform(-4, 4, n), rng.uniform(0.2, 3.0, n)])
    first = np.concatenate([np.arange(n - 1), np.arange(n - 2)])
    second = np.concatenate([np.arange(1, n), np.arange(2, n)])
    rest = np.linalg.norm(positions[second] - positions[first], axis=1)
    s = len(first)
    k = rng.uniform(5, 15, s)
    skull_x, skull_y = np.meshgrid(np.linspace(-8, 8, 5), np.linspace(-8, 8, 5))
    skull = np.column_stack([skull_x.ravel(), skull_y.ravel(), np.zeros(25)])
    index = np.arange(25).reshape(5, 5)
    faces = []
    for r in range(4):
        for c in range(4):
            a, b, d, e = index[r, c], index[r, c + 1], index[r + 1, c], index[r + 1, c + 1]
            faces += [(a, b, d), (b, e, d)]
    faces = np.array(faces)
    edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)
    both = np.concatenate([edges, edges[:, ::-1]])
    both = both[np.lexsort((both[:, 1], both[:, 0]))]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(both[:, 0], minlength=25))])
    corner_order = np.argsort(faces.reshape(-1), kind="stable")
    face_indptr = np.concatenate([[0], np.cumsum(np.bincount(faces.reshape(-1), minlength=25))])
    bones = (skull[:, 1] < -6).astype(np.int64)  # the bottom row on the mandible
    return SkinArrays(
        masses=rng.uniform(0.5, 1.5, n), spring_first=first, spring_second=second, spring_rest=rest,
        spring_stiffness=k, spring_stiffness_high=3 * k, spring_knee=np.full(s, 0.05),
        spring_damping=rng.uniform(0.1, 0.3, s),
        anchor_particle=np.arange(n), anchor_target=positions, anchor_bone=(np.arange(n) % 2).astype(np.int64),
        anchor_stiffness=rng.uniform(2.0, 6.0, n), anchor_damping=rng.uniform(0.1, 0.2, n), drag=2.0,
        muscle_kind=np.array([0, 1]), muscle_bone=np.array([1, 0]),
        muscle_point=np.array([[6.0, 1.0, -1.0], [0.5, 0.2, 1.0]]),
        muscle_axes=np.array([[0, 0, 0, 0, 0, 0], [1.0, 0, 0, 0, 1.0, 0]]), muscle_max_force=np.array([30.0, 20.0]),
        muscle_indptr=np.array([0, 3, 6]), muscle_particles=np.array([1, 2, 3, 2, 4, 5]),
        muscle_weights=np.array([0.2, 0.5, 0.3, 0.3, 0.3, 0.4]),
        skull_vertices=skull, skull_normals=np.tile([0.0, 0.0, 1.0], (25, 1)), skull_faces=faces,
        skull_face_indptr=face_indptr, skull_vertex_faces=corner_order // 3, skull_face_rim=rim_edges(faces, 25, bones),
        skull_bone=bones, skull_indptr=indptr, skull_neighbours=both[:, 1],
        particle_foot=np.argmin(np.linalg.norm(positions[:, None, :2] - skull[None, :, :2], axis=2), axis=1),
        contact_stiffness=np.full(n, 40.0), contact_damping=np.full(n, 0.5), contact_margin=0.5,
        jaw_pivot=np.array([0.0, 5.0, -20.0]), jaw_axis=np.array([1.0, 0.0, 0.0]),
        **_random_prisms(positions, rng),
    ).validated()


def _random_prisms(positions, rng) -> dict:
    """Two prisms over the chain's particles, each corner order chosen so that its
    volume at the anchors' positions is positive, with rest volumes a little off it (a
    pressure at rest)."""
    n = len(positions)
    particles, volume = oriented_prisms(np.array([np.arange(6), np.arange(1, 7) % n]), positions)
    return dict(prism_particles=particles, prism_rest_volume=np.abs(volume) * rng.uniform(0.8, 1.2, 2) + 0.5,
                prism_stiffness=rng.uniform(0.5, 2.0, 2))

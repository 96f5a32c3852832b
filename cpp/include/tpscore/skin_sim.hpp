// A layered mass-spring-damper skin over a skull, driven by muscles: force
// accumulation, two integrators (semi-implicit Euler and linearised backward Euler),
// skull contact, and a run loop that stops when the skin has settled.
//
// The model (after Lee, Terzopoulos and Waters, "Realistic modeling for facial
// animation", 1995, as the head-adaptation method uses it):
// - particles with masses; damped springs between them whose force is biphasic
//   (one slope up to a knee strain, a steeper one beyond, the same in compression);
// - anchors: isotropic damped springs of zero rest length from a particle to a point
//   fixed to a bone (the skull, or the mandible, which rotates with the jaw);
// - muscles: linear (toward an attachment point) or sphincter (toward an epicentre,
//   in the ellipse's plane), each pulling a fixed set of particles with fixed weights,
//   the pull fading to zero within 1 mm of the attachment (or the sphincter's axis);
// - volume: each prism of tissue between two layers (a skin triangle over the same
//   triangle below) keeps its volume, with energy k (V - V0)^2 / 2 for its volume V
//   (three tetrahedra); tissue squeezed in one direction bulges in the others, as
//   nearly incompressible soft tissue does, instead of folding in place;
// - drag: a force -drag * m * v on every particle, which settles slow modes;
// - skull contact: with h the signed distance of a particle to the skull (to the
//   closest point of the triangles near its nearest skull vertex; N the unit
//   direction out of the skull there), a damped penalty force (k_c (margin - h) -
//   c_c v.N) N pushes it out while h < margin (per particle, below its rest height),
//   N blended over the triangles nearly as close as the closest one (continuous across
//   a concave crease, where the closest point jumps); a particle that still gets inside
//   (h < 0) is moved back onto the skull, and its inward velocity is removed. The
//   penalty makes a resting contact a true equilibrium of the forces; the projection
//   guarantees that nothing ends inside the skull. Each particle meets only the
//   bone it rests on (skull or mandible); where its closest point lies on that bone's
//   rim (the outline, the seam to the other bone) it is beside the bone, at its
//   distance from the rim.
//
// Units are the caller's; tpscore uses mm, g and s (forces in g mm / s^2 = 1e-6 N).
// Every per-particle quantity is gathered row by row in a fixed order, so results
// do not depend on the thread count.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "tpscore/sparse_solve.hpp"
#include "tpscore/types.hpp"

namespace tpscore {

/// Bones a point can be fixed to.
enum SkinBone : std::int64_t { kSkull = 0, kMandible = 1 };
/// Muscle kinds.
enum SkinMuscleKind : std::int64_t { kLinearMuscle = 0, kSphincterMuscle = 1 };
/// A prism of tissue: three particles of a triangle over the same triangle's three below.
using Prisms = Eigen::Matrix<std::int64_t, Eigen::Dynamic, 6, Eigen::RowMajor>;
/// Integrators.
/// - symplectic: semi-implicit Euler, v += dt f / m, x += dt v; stable below a step set
///   by the stiffest spring (the caller picks it).
/// - implicit: linearised backward Euler (Baraff and Witkin, "Large steps in cloth
///   simulation", 1998): each step solves (M + dt D + dt^2 K) dv = dt (f - dt K v)
///   with K = -df/dx and D = -df/dv at the current state (the prisms' volume term by
///   its Gauss-Newton part k g g^T, g the volume's gradient), assembled into one sparsity
///   pattern (analysed once) and factorised by tpscore::PatternCholesky. Stable at
///   large steps; each step costs a sparse factorisation.
enum class SkinIntegrator : int { symplectic = 0, implicit = 1 };

/// The fields that define a skin system, listed once: X(type, name) for each, in the
/// order the binding takes them. SkinSystemData declares them and the binding
/// (bind_skin_sim.cpp) takes and copies them by expanding this list; Python lists
/// them in tpscore.physics.system.SKIN_FIELDS.
/// Shapes: n particles, s springs, a anchors, k muscles, v skull vertices, f triangles,
/// p prisms.
#define TPSCORE_SKIN_FIELDS(X)                                                                     \
    X(VectorX, masses)                /* (n,) */                                                   \
    X(IndexVector, spring_first)      /* (s,) particle indices, first != second */                 \
    X(IndexVector, spring_second)     /* (s,) */                                                   \
    X(VectorX, spring_rest)           /* (s,) rest length */                                       \
    X(VectorX, spring_stiffness)      /* (s,) slope below the knee */                              \
    X(VectorX, spring_stiffness_high) /* (s,) slope beyond the knee */                             \
    X(VectorX, spring_knee)           /* (s,) knee strain |l - l0| / l0 */                         \
    X(VectorX, spring_damping)        /* (s,) along the spring */                                  \
    X(IndexVector, anchor_particle)   /* (a,) */                                                   \
    X(Points, anchor_target)          /* (a, 3) rest position of the anchor point */               \
    X(IndexVector, anchor_bone)       /* (a,) SkinBone */                                          \
    X(VectorX, anchor_stiffness)      /* (a,) */                                                   \
    X(VectorX, anchor_damping)        /* (a,) */                                                   \
    X(double, drag)                   /* mass-proportional damping rate (1 / time) */              \
    X(IndexVector, muscle_kind)       /* (k,) SkinMuscleKind */                                    \
    X(IndexVector, muscle_bone)       /* (k,) bone the attachment / epicentre is fixed to */       \
    X(Points, muscle_point)           /* (k, 3) attachment (linear) or epicentre (sphincter) */    \
    X(MatrixX, muscle_axes)           /* (k, 6) a sphincter's two unit axes (unused for linear) */ \
    X(VectorX, muscle_max_force)      /* (k,) force at contraction 1, summed over the particles */ \
    X(IndexVector, muscle_indptr)     /* (k + 1,) CSR rows of the muscles' particles */            \
    X(IndexVector, muscle_particles)  /* particles each muscle pulls */                            \
    X(VectorX, muscle_weights)        /* their weights (a muscle's weights sum to 1) */            \
    X(Points, skull_vertices)         /* (v, 3) rest positions */                                  \
    X(Points, skull_normals)          /* (v, 3) unit outward normals at rest */                    \
    X(Faces, skull_faces)             /* (f, 3) triangles, oriented outward */                     \
    X(IndexVector, skull_face_indptr) /* (v + 1,) CSR: the triangles the contact search */         \
    X(IndexVector, skull_vertex_faces) /* tries near each vertex (its two-ring, in order) */       \
    X(IndexVector, skull_face_rim)    /* (f,) bit k: the edge opposite corner k is on the rim */   \
    X(IndexVector, skull_bone)        /* (v,) SkinBone */                                          \
    X(IndexVector, skull_indptr)      /* (v + 1,) CSR vertex adjacency of the skull mesh */        \
    X(IndexVector, skull_neighbours)  /* neighbour vertex indices */                               \
    X(IndexVector, particle_foot)     /* (n,) first skull vertex to search from; -1: no contact */ \
    X(VectorX, contact_stiffness)     /* (n,) k_c of the penalty (0: projection only) */           \
    X(VectorX, contact_damping)       /* (n,) c_c of the penalty */                                \
    X(VectorX, contact_margin)        /* (n,) height over the skull where the penalty starts */    \
    X(Eigen::Vector3d, jaw_pivot)     /* a point on the jaw's axis */                              \
    X(Eigen::Vector3d, jaw_axis)      /* unit axis (the head's x) */                               \
    X(Prisms, prism_particles)        /* (p, 6) top a, b, c, then the three below (distinct) */    \
    X(VectorX, prism_rest_volume)     /* (p,) signed volume at rest (> 0) */                       \
    X(VectorX, prism_stiffness)       /* (p,) k of the energy k (V - V0)^2 / 2 */

/// Everything that defines a skin system; all arrays are copied at construction.
/// Preconditions (checked by the Python layer): sizes consistent, indices in range,
/// masses > 0, stiffnesses and dampings >= 0, rest lengths > 0, axes unit length.
struct SkinSystemData {
#define TPSCORE_SKIN_MEMBER(T, name) T name{};
    TPSCORE_SKIN_FIELDS(TPSCORE_SKIN_MEMBER)
#undef TPSCORE_SKIN_MEMBER

    /// Per particle, the stiffness a unit displacement meets at rest (sum of the low
    /// slopes of its springs and anchors): the rest detector's force-to-length scale.
    /// Filled by the system; callers leave it empty.
    VectorX rest_stiffness;
};

/// Positions, velocities and the contact search's current skull vertex per particle.
struct SkinState {
    Points positions;   ///< (n, 3)
    Points velocities;  ///< (n, 3)
    IndexVector foot;   ///< (n,)
};

/// The skull at one jaw angle.
struct SkullGeometry {
    Points vertices;      ///< (v, 3)
    Points normals;       ///< (v, 3) unit vertex normals
    Points face_normals;  ///< (f, 3) unit triangle normals
};

/// Where a particle meets the skull.
struct SkullContact {
    double height = 0.0;  ///< signed distance, > 0 outside
    Eigen::Vector3d normal = Eigen::Vector3d::Zero();  ///< unit, out of the skull
    Eigen::Vector3d point = Eigen::Vector3d::Zero();   ///< the closest skull point
    std::int64_t face = -1;                     ///< its triangle (-1: a vertex's plane)
};

/// Time-dependent inputs of one step.
struct SkinControls {
    VectorX contractions;    ///< (k,) in [0, 1] (scaled by the ramp in a run)
    double jaw_angle = 0.0;  ///< radians about jaw_axis through jaw_pivot
};

/// Settings of a run: a ramp from rest to the target controls, then until settled.
struct SkinRunSettings {
    SkinIntegrator integrator = SkinIntegrator::symplectic;
    double dt = 1e-4;
    std::int64_t max_steps = 10000;
    /// Controls rise as smoothstep(t / ramp_time) (3 s^2 - 2 s^3) to their target;
    /// 0 applies them at once.
    double ramp_time = 0.0;
    /// Settled: after the ramp, for `patience` consecutive steps, every particle's speed
    /// is below velocity_tolerance and its net force below rest_stiffness *
    /// force_tolerance (a length: how far the force would move it at rest).
    double velocity_tolerance = 0.5;
    double force_tolerance = 1e-3;
    std::int64_t patience = 5;
    /// Test for rest every this many steps (the test costs one force evaluation).
    std::int64_t check_every = 1;
    /// Stop as diverged when a value is not finite or a particle is farther than this
    /// from its rest position.
    double divergence_distance = 200.0;
    /// Keep the first record_count particles' positions every record_every steps
    /// (and at the last step); 0 records nothing.
    std::int64_t record_every = 0;
    std::int64_t record_count = 0;
};

/// What a run did.
struct SkinRunReport {
    std::int64_t steps = 0;
    bool settled = false;
    bool diverged = false;
    double time = 0.0;          ///< simulated time at the end
    double max_speed = 0.0;     ///< at the last step
    double max_residual = 0.0;  ///< largest |f| / rest_stiffness at the last step
    std::vector<double> frame_times;
    std::vector<double> frames;  ///< frame after frame of (record_count, 3) positions
};

/// Rotation of the jaw by `angle` radians about `axis` (unit) through `pivot`.
struct JawMotion {
    Eigen::Matrix3d rotation;
    Eigen::Vector3d pivot;
    JawMotion(const Eigen::Vector3d& pivot, const Eigen::Vector3d& axis, double angle);
    Eigen::Vector3d apply(const Eigen::Vector3d& point, std::int64_t bone) const;
};

class SkinSystem {
public:
    explicit SkinSystem(SkinSystemData data);

    std::int64_t particles() const { return static_cast<std::int64_t>(data_.masses.size()); }
    std::int64_t muscles() const { return static_cast<std::int64_t>(data_.muscle_kind.size()); }
    const SkinSystemData& data() const { return data_; }

    /// Net force (n, 3) on every particle.
    Points forces(const SkinState& state, const SkinControls& controls) const;

    /// Elastic energy of the springs, anchors and prisms (muscles and damping excluded).
    double potential_energy(const PointsRef& positions, const SkinControls& controls) const;
    /// sum m |v|^2 / 2.
    double kinetic_energy(const PointsRef& velocities) const;

    /// Skull contact: updates each particle's nearest skull vertex, and moves a particle
    /// found inside the skull back onto it (see above).
    void project_contacts(SkinState& state, const SkinControls& controls) const;
    /// Each particle's signed height over the skull near its skull vertex `foot`
    /// (positive outside; 0 where foot < 0 or the head has no skull), at the controls'
    /// jaw angle: what the contact penalty tests against the margin.
    VectorX skull_heights(const PointsRef& positions, const Eigen::Ref<const IndexVector>& foot,
                          const SkinControls& controls) const;

    /// The net force less what the skull bears: for a particle lying on the skull (moved
    /// there by the projection), the part of its force pushing into the skull is
    /// removed. What the rest detector tests.
    Points free_forces(const SkinState& state, const SkinControls& controls) const;

    /// One step of length dt with the controls held fixed, contact included.
    /// The implicit step keeps its factorisation in the system: it is not safe to step
    /// one system from several threads at once.
    void step(SkinState& state, const SkinControls& controls, double dt,
              SkinIntegrator integrator);

    /// Steps from `state` with the controls ramped to `target` until settled,
    /// diverged or out of steps.
    SkinRunReport run(SkinState& state, const SkinControls& target,
                      const SkinRunSettings& settings);

private:
    struct Incidence {
        std::int64_t spring;
        std::int64_t other;
    };

    SkinSystemData data_;
    // Per particle (CSR): incident springs, anchors, and (muscle, weight) pairs.
    std::vector<std::int64_t> spring_offsets_;
    std::vector<Incidence> spring_incidence_;
    std::vector<std::int64_t> anchor_offsets_;
    std::vector<std::int64_t> anchor_index_;
    std::vector<std::int64_t> muscle_offsets_;
    std::vector<std::int64_t> muscle_of_entry_;
    std::vector<double> weight_of_entry_;
    std::vector<std::int64_t> prism_offsets_;
    std::vector<std::int64_t> prism_corner_;  // prism * 6 + corner, per particle

    // The implicit system's pattern: lower triangle of the (3n x 3n) matrix, block
    // column by block column; for each particle, the position of its diagonal block's
    // three columns and, per incident spring to a higher-indexed particle, the
    // position of the off-diagonal block.
    std::vector<std::int64_t> pattern_indptr_, pattern_indices_;
    std::vector<std::int64_t> spring_block_;  // (s,) slot of block (higher, lower) in column lower
    // (p * 36): for corners (c, r) of a prism, the slot of block (corner r, corner c) in
    // corner c's column when r's particle is the higher one, else -1.
    std::vector<std::int64_t> prism_block_;
    std::unique_ptr<PatternCholesky> factor_;  // the implicit step's, refactorised every step
    std::vector<double> skull_rise_;   // (v,) how far its listed triangles rise over its plane
    double max_margin_ = 0.0;          // the largest contact margin

    void build_pattern();
    /// Lower-triangle CSC values of M + dt D + dt^2 K linearised at `state`, and K v per
    /// particle into kv.
    void assemble(const SkinState& state, const SkinControls& controls, double dt,
                  std::vector<double>& values, Points& kv) const;
    SkullGeometry skull_at(const SkinControls& controls) const;
    SkullContact locate(const Eigen::Vector3d& x, std::int64_t foot, const SkullGeometry& skull) const;
    Points bone_points(const Points& points, const IndexVector& bones,
                       const JawMotion& jaw) const;
    Points muscle_points(const JawMotion& jaw) const;
    void accumulate_forces(const SkinState& state, const SkinControls& controls,
                           const Points& anchors, const Points& muscle_points,
                           const SkullGeometry& skull, Points& out) const;
    void step_symplectic(SkinState& state, const SkinControls& controls, double dt) const;
    void step_implicit(SkinState& state, const SkinControls& controls, double dt);
};

}  // namespace tpscore

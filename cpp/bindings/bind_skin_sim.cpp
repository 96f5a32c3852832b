// Bindings of the layered skin simulation. The arrays arrive validated from
// tpscore.physics (float64 C-contiguous, int64 indices in range); states go in and
// come out as owning NumPy arrays. Every call runs with the GIL released.
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/stl/tuple.h>

#include <cstdint>
#include <stdexcept>
#include <tuple>

#include "tpscore/skin_sim.hpp"

namespace nb = nanobind;
using namespace nb::literals;

namespace {
using tpscore::IndexVector;
using tpscore::MatrixX;
using tpscore::Points;
using tpscore::SkinControls;
using tpscore::SkinState;
using tpscore::SkinSystem;
using tpscore::VectorX;
using IndexRef = Eigen::Ref<const IndexVector>;
using VectorRef = Eigen::Ref<const VectorX>;
using PointsIn = Eigen::Ref<const Points>;
using MatrixIn = Eigen::Ref<const MatrixX>;

SkinState make_state(const SkinSystem& system, const PointsIn& positions,
                     const PointsIn& velocities, const IndexRef& foot) {
    const Eigen::Index n = static_cast<Eigen::Index>(system.particles());
    if (positions.rows() != n || velocities.rows() != n || foot.size() != n)
        throw std::invalid_argument("positions, velocities and foot need one row per particle");
    return SkinState{positions, velocities, foot};
}

SkinControls make_controls(const SkinSystem& system, const VectorRef& contractions,
                           double jaw_angle) {
    if (contractions.size() != system.muscles())
        throw std::invalid_argument("contractions needs one value per muscle");
    return SkinControls{contractions, jaw_angle};
}
}  // namespace

void bind_skin_sim(nb::module_& m) {
    nb::enum_<tpscore::SkinIntegrator>(m, "SkinIntegrator", "How a step integrates the skin's motion.")
        .value("symplectic", tpscore::SkinIntegrator::symplectic)
        .value("implicit", tpscore::SkinIntegrator::implicit);
    nb::class_<SkinSystem>(m, "SkinSystem",
                           "Layered mass-spring-damper skin (use tpscore.physics.SkinModel).")
        .def(
            "__init__",
            [](SkinSystem* self, const VectorRef& masses, const IndexRef& spring_first,
               const IndexRef& spring_second, const VectorRef& spring_rest,
               const VectorRef& spring_stiffness, const VectorRef& spring_stiffness_high,
               const VectorRef& spring_knee, const VectorRef& spring_damping,
               const IndexRef& anchor_particle, const PointsIn& anchor_target,
               const IndexRef& anchor_bone, const VectorRef& anchor_stiffness,
               const VectorRef& anchor_damping, double drag, const IndexRef& muscle_kind,
               const IndexRef& muscle_bone, const PointsIn& muscle_point,
               const MatrixIn& muscle_axes, const VectorRef& muscle_max_force,
               const IndexRef& muscle_indptr, const IndexRef& muscle_particles,
               const VectorRef& muscle_weights, const PointsIn& skull_vertices,
               const PointsIn& skull_normals, const Eigen::Ref<const tpscore::Faces>& skull_faces,
               const IndexRef& skull_face_indptr, const IndexRef& skull_vertex_faces,
               const IndexRef& skull_face_rim,
               const IndexRef& skull_bone,
               const IndexRef& skull_indptr, const IndexRef& skull_neighbours,
               const IndexRef& particle_foot, const VectorRef& contact_stiffness,
               const VectorRef& contact_damping,
               const VectorRef& contact_margin,
               const Eigen::Vector3d& jaw_pivot, const Eigen::Vector3d& jaw_axis) {
                tpscore::SkinSystemData data;
                data.masses = masses;
                data.spring_first = spring_first;
                data.spring_second = spring_second;
                data.spring_rest = spring_rest;
                data.spring_stiffness = spring_stiffness;
                data.spring_stiffness_high = spring_stiffness_high;
                data.spring_knee = spring_knee;
                data.spring_damping = spring_damping;
                data.anchor_particle = anchor_particle;
                data.anchor_target = anchor_target;
                data.anchor_bone = anchor_bone;
                data.anchor_stiffness = anchor_stiffness;
                data.anchor_damping = anchor_damping;
                data.drag = drag;
                data.muscle_kind = muscle_kind;
                data.muscle_bone = muscle_bone;
                data.muscle_point = muscle_point;
                data.muscle_axes = muscle_axes;
                data.muscle_max_force = muscle_max_force;
                data.muscle_indptr = muscle_indptr;
                data.muscle_particles = muscle_particles;
                data.muscle_weights = muscle_weights;
                data.skull_vertices = skull_vertices;
                data.skull_normals = skull_normals;
                data.skull_faces = skull_faces;
                data.skull_face_indptr = skull_face_indptr;
                data.skull_vertex_faces = skull_vertex_faces;
                data.skull_face_rim = skull_face_rim;
                data.skull_bone = skull_bone;
                data.skull_indptr = skull_indptr;
                data.skull_neighbours = skull_neighbours;
                data.particle_foot = particle_foot;
                data.contact_stiffness = contact_stiffness;
                data.contact_damping = contact_damping;
                data.contact_margin = contact_margin;
                data.jaw_pivot = jaw_pivot;
                data.jaw_axis = jaw_axis;
                nb::gil_scoped_release release;
                new (self) SkinSystem(std::move(data));
            },
            "masses"_a, "spring_first"_a, "spring_second"_a, "spring_rest"_a,
            "spring_stiffness"_a, "spring_stiffness_high"_a, "spring_knee"_a, "spring_damping"_a,
            "anchor_particle"_a, "anchor_target"_a, "anchor_bone"_a, "anchor_stiffness"_a,
            "anchor_damping"_a, "drag"_a, "muscle_kind"_a, "muscle_bone"_a, "muscle_point"_a,
            "muscle_axes"_a, "muscle_max_force"_a, "muscle_indptr"_a, "muscle_particles"_a,
            "muscle_weights"_a, "skull_vertices"_a, "skull_normals"_a, "skull_faces"_a,
            "skull_face_indptr"_a, "skull_vertex_faces"_a, "skull_face_rim"_a, "skull_bone"_a,
            "skull_indptr"_a, "skull_neighbours"_a, "particle_foot"_a, "contact_stiffness"_a, "contact_damping"_a, "contact_margin"_a,
            "jaw_pivot"_a, "jaw_axis"_a)
        .def_prop_ro("particles", &SkinSystem::particles)
        .def_prop_ro("muscles", &SkinSystem::muscles)
        .def_prop_ro("rest_stiffness", [](const SkinSystem& s) { return s.data().rest_stiffness; })
        .def(
            "forces",
            [](const SkinSystem& s, const PointsIn& positions, const PointsIn& velocities,
               const IndexRef& foot, const VectorRef& contractions, double jaw_angle) {
                const SkinState state = make_state(s, positions, velocities, foot);
                return s.forces(state, make_controls(s, contractions, jaw_angle));
            },
            "positions"_a, "velocities"_a, "foot"_a, "contractions"_a, "jaw_angle"_a,
            nb::call_guard<nb::gil_scoped_release>(),
            "Net force (n, 3) on every particle (contact penalty at the given skull vertices).")
        .def(
            "potential_energy",
            [](const SkinSystem& s, const PointsIn& positions, const VectorRef& contractions,
               double jaw_angle) {
                return s.potential_energy(positions, make_controls(s, contractions, jaw_angle));
            },
            "positions"_a, "contractions"_a, "jaw_angle"_a,
            nb::call_guard<nb::gil_scoped_release>(), "Elastic energy of springs and anchors.")
        .def("kinetic_energy", &SkinSystem::kinetic_energy, "velocities"_a,
             nb::call_guard<nb::gil_scoped_release>())
        .def(
            "project_contacts",
            [](const SkinSystem& s, const PointsIn& positions, const PointsIn& velocities,
               const IndexRef& foot, double jaw_angle) {
                SkinState state = make_state(s, positions, velocities, foot);
                SkinControls controls{VectorX::Zero(s.muscles()), jaw_angle};
                s.project_contacts(state, controls);
                return std::make_tuple(std::move(state.positions), std::move(state.velocities),
                                       std::move(state.foot));
            },
            "positions"_a, "velocities"_a, "foot"_a, "jaw_angle"_a,
            nb::call_guard<nb::gil_scoped_release>())
        .def(
            "skull_heights",
            [](const SkinSystem& s, const PointsIn& positions, const IndexRef& foot, double jaw_angle) {
                return s.skull_heights(positions, foot, SkinControls{VectorX::Zero(s.muscles()), jaw_angle});
            },
            "positions"_a, "foot"_a, "jaw_angle"_a, nb::call_guard<nb::gil_scoped_release>(),
            "Signed height (n,) of each particle over the skull near its skull vertex.")
        .def(
            "step",
            [](SkinSystem& s, const PointsIn& positions, const PointsIn& velocities,
               const IndexRef& foot, const VectorRef& contractions, double jaw_angle, double dt,
               tpscore::SkinIntegrator integrator, std::int64_t steps) {
                SkinState state = make_state(s, positions, velocities, foot);
                const SkinControls controls = make_controls(s, contractions, jaw_angle);
                for (std::int64_t k = 0; k < steps; ++k)
                    s.step(state, controls, dt, integrator);
                return std::make_tuple(std::move(state.positions), std::move(state.velocities),
                                       std::move(state.foot));
            },
            "positions"_a, "velocities"_a, "foot"_a, "contractions"_a, "jaw_angle"_a, "dt"_a,
            "integrator"_a, "steps"_a, nb::call_guard<nb::gil_scoped_release>(),
            "`steps` steps with fixed controls.")
        .def(
            "free_forces",
            [](const SkinSystem& s, const PointsIn& positions, const PointsIn& velocities,
               const IndexRef& foot, const VectorRef& contractions, double jaw_angle) {
                const SkinState state = make_state(s, positions, velocities, foot);
                return s.free_forces(state, make_controls(s, contractions, jaw_angle));
            },
            "positions"_a, "velocities"_a, "foot"_a, "contractions"_a, "jaw_angle"_a,
            nb::call_guard<nb::gil_scoped_release>(),
            "Net force less what the skull bears (what the rest detector tests).")
        .def(
            "run",
            [](SkinSystem& s, const PointsIn& positions, const PointsIn& velocities,
               const IndexRef& foot, const VectorRef& contractions, double jaw_angle,
               tpscore::SkinIntegrator integrator, double dt, std::int64_t max_steps, double ramp_time,
               double velocity_tolerance, double force_tolerance, std::int64_t patience,
               std::int64_t check_every, double divergence_distance, std::int64_t record_every,
               std::int64_t record_count) {
                SkinState state = make_state(s, positions, velocities, foot);
                const SkinControls target = make_controls(s, contractions, jaw_angle);
                if (record_count < 0 || record_count > s.particles())
                    throw std::invalid_argument("record_count must lie in [0, particles]");
                tpscore::SkinRunSettings settings;
                settings.integrator = integrator;
                settings.dt = dt;
                settings.max_steps = max_steps;
                settings.ramp_time = ramp_time;
                settings.velocity_tolerance = velocity_tolerance;
                settings.force_tolerance = force_tolerance;
                settings.patience = patience;
                settings.check_every = check_every;
                settings.divergence_distance = divergence_distance;
                settings.record_every = record_every;
                settings.record_count = record_count;
                tpscore::SkinRunReport report = s.run(state, target, settings);
                const Eigen::Index frames = static_cast<Eigen::Index>(report.frame_times.size());
                Points frame_points(frames * record_count, 3);
                for (Eigen::Index i = 0; i < frame_points.rows(); ++i)
                    for (int c = 0; c < 3; ++c) frame_points(i, c) = report.frames[3 * i + c];
                VectorX times = Eigen::Map<const VectorX>(report.frame_times.data(), frames);
                return std::make_tuple(std::move(state.positions), std::move(state.velocities),
                                       std::move(state.foot), report.steps, report.settled,
                                       report.diverged, report.time, report.max_speed,
                                       report.max_residual, std::move(times),
                                       std::move(frame_points));
            },
            "positions"_a, "velocities"_a, "foot"_a, "contractions"_a, "jaw_angle"_a,
            "integrator"_a, "dt"_a, "max_steps"_a, "ramp_time"_a, "velocity_tolerance"_a,
            "force_tolerance"_a, "patience"_a, "check_every"_a, "divergence_distance"_a,
            "record_every"_a, "record_count"_a, nb::call_guard<nb::gil_scoped_release>(),
            "Ramp the controls up and step until settled; returns the state, the report and "
            "the recorded frames.");
}

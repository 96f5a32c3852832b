// Bindings of the layered skin simulation. The arrays arrive validated from
// tpscore.physics (float64 C-contiguous, int64 indices in range); states go in as
// In<T> views and come out as owning NumPy arrays (arrays.hpp). Every call runs with
// the GIL released.
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/stl/tuple.h>

#include <cstdint>
#include <stdexcept>
#include <tuple>

#include "arrays.hpp"
#include "tpscore/skin_sim.hpp"

namespace nb = nanobind;
using namespace nb::literals;
using tpscore_bindings::In;

namespace {
using tpscore::Faces;
using tpscore::IndexVector;
using tpscore::MatrixX;
using tpscore::Points;
using tpscore::Prisms;
using tpscore::SkinControls;
using tpscore::SkinState;
using tpscore::SkinSystem;
using tpscore::VectorX;
using PointsIn = In<Points>;
using IndexIn = In<IndexVector>;
using VectorIn = In<VectorX>;

// The argument that carries a field of type T: a view of an array, a scalar by value.
template <class T>
struct FieldArgument {
    using type = In<T>;
};
template <>
struct FieldArgument<double> {
    using type = double;
};

SkinState make_state(const SkinSystem& system, PointsIn positions, PointsIn velocities, IndexIn foot) {
    const Eigen::Index n = static_cast<Eigen::Index>(system.particles());
    if (positions.rows() != n || velocities.rows() != n || foot.size() != n)
        throw std::invalid_argument("positions, velocities and foot need one row per particle");
    return SkinState{positions, velocities, foot};
}

SkinControls make_controls(const SkinSystem& system, VectorIn contractions, double jaw_angle) {
    if (contractions.size() != system.muscles())
        throw std::invalid_argument("contractions needs one value per muscle");
    return SkinControls{contractions, jaw_angle};
}
}  // namespace

// One parameter, one copy into SkinSystemData and one keyword per field of
// TPSCORE_SKIN_FIELDS (tpscore/skin_sim.hpp).
#define TPSCORE_SKIN_PARAMETER(T, name) , typename FieldArgument<T>::type name
#define TPSCORE_SKIN_COPY(T, name) data.name = name;
#define TPSCORE_SKIN_KEYWORD(T, name) , nb::arg(#name)

void bind_skin_sim(nb::module_& m) {
    nb::enum_<tpscore::SkinIntegrator>(m, "SkinIntegrator", "How a step integrates the skin's motion.")
        .value("symplectic", tpscore::SkinIntegrator::symplectic)
        .value("implicit", tpscore::SkinIntegrator::implicit);
    nb::class_<SkinSystem>(m, "SkinSystem",
                           "Layered mass-spring-damper skin (use tpscore.physics.SkinModel).")
        .def(
            "__init__",
            [](SkinSystem* self TPSCORE_SKIN_FIELDS(TPSCORE_SKIN_PARAMETER)) {
                tpscore::SkinSystemData data;
                TPSCORE_SKIN_FIELDS(TPSCORE_SKIN_COPY)
                nb::gil_scoped_release release;
                new (self) SkinSystem(std::move(data));
            } TPSCORE_SKIN_FIELDS(TPSCORE_SKIN_KEYWORD))
        .def_prop_ro("particles", &SkinSystem::particles)
        .def_prop_ro("muscles", &SkinSystem::muscles)
        .def_prop_ro("rest_stiffness", [](const SkinSystem& s) { return s.data().rest_stiffness; })
        .def(
            "forces",
            [](const SkinSystem& s, PointsIn positions, PointsIn velocities,
               IndexIn foot, VectorIn contractions, double jaw_angle) {
                const SkinState state = make_state(s, positions, velocities, foot);
                return s.forces(state, make_controls(s, contractions, jaw_angle));
            },
            "positions"_a, "velocities"_a, "foot"_a, "contractions"_a, "jaw_angle"_a,
            nb::call_guard<nb::gil_scoped_release>(),
            "Net force (n, 3) on every particle (contact penalty at the given skull vertices).")
        .def(
            "potential_energy",
            [](const SkinSystem& s, PointsIn positions, VectorIn contractions,
               double jaw_angle) {
                return s.potential_energy(positions, make_controls(s, contractions, jaw_angle));
            },
            "positions"_a, "contractions"_a, "jaw_angle"_a,
            nb::call_guard<nb::gil_scoped_release>(), "Elastic energy of springs and anchors.")
        .def("kinetic_energy", [](const SkinSystem& s, PointsIn velocities) { return s.kinetic_energy(velocities); },
             "velocities"_a, nb::call_guard<nb::gil_scoped_release>())
        .def(
            "project_contacts",
            [](const SkinSystem& s, PointsIn positions, PointsIn velocities,
               IndexIn foot, double jaw_angle) {
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
            [](const SkinSystem& s, PointsIn positions, IndexIn foot, double jaw_angle) {
                return s.skull_heights(positions, foot, SkinControls{VectorX::Zero(s.muscles()), jaw_angle});
            },
            "positions"_a, "foot"_a, "jaw_angle"_a, nb::call_guard<nb::gil_scoped_release>(),
            "Signed height (n,) of each particle over the skull near its skull vertex.")
        .def(
            "step",
            [](SkinSystem& s, PointsIn positions, PointsIn velocities,
               IndexIn foot, VectorIn contractions, double jaw_angle, double dt,
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
            [](const SkinSystem& s, PointsIn positions, PointsIn velocities,
               IndexIn foot, VectorIn contractions, double jaw_angle) {
                const SkinState state = make_state(s, positions, velocities, foot);
                return s.free_forces(state, make_controls(s, contractions, jaw_angle));
            },
            "positions"_a, "velocities"_a, "foot"_a, "contractions"_a, "jaw_angle"_a,
            nb::call_guard<nb::gil_scoped_release>(),
            "Net force less what the skull bears (what the rest detector tests).")
        .def(
            "run",
            [](SkinSystem& s, PointsIn positions, PointsIn velocities,
               IndexIn foot, VectorIn contractions, double jaw_angle,
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

#undef TPSCORE_SKIN_PARAMETER
#undef TPSCORE_SKIN_COPY
#undef TPSCORE_SKIN_KEYWORD

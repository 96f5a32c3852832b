// nanobind glue for the rigid ICP (tpscore/rigid_icp.hpp). Inputs arrive validated and
// C-contiguous from tpscore.expression.alignment; the ICP runs with the GIL released.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/tuple.h>

#include <cstdint>
#include <stdexcept>

#include "tpscore/rigid_icp.hpp"

namespace nb = nanobind;
using namespace nb::literals;

namespace {
template <class Shape>
using Input = nb::ndarray<const double, Shape, nb::c_contig, nb::device::cpu>;
}  // namespace

void bind_rigid_icp(nb::module_& m) {
    m.def(
        "rigid_icp",
        [](const tpscore::MeshSurface& fixed, Input<nb::shape<-1, 3>> face_normals, Input<nb::shape<-1, 3>> sample,
           Input<nb::shape<-1>> prior, Input<nb::shape<4, 4>> start, int iterations, double tukey_factor,
           double min_scale, double tolerance) {
            if (static_cast<std::int64_t>(face_normals.shape(0)) != fixed.num_triangles())
                throw std::invalid_argument("face_normals must have one row per triangle of the surface");
            if (prior.shape(0) != sample.shape(0))
                throw std::invalid_argument("prior must have one entry per sample point");
            const Eigen::Map<const tpscore::Points> points(sample.data(), static_cast<Eigen::Index>(sample.shape(0)), 3);
            const Eigen::Map<const Eigen::Matrix<double, 4, 4, Eigen::RowMajor>> start_matrix(start.data());
            const tpscore::RigidIcpSettings settings{iterations, tukey_factor, min_scale, tolerance};
            tpscore::RigidIcpResult result;
            {
                nb::gil_scoped_release release;
                result = tpscore::rigid_icp(fixed, face_normals.data(), points, prior.data(),
                                            Eigen::Matrix4d(start_matrix), settings);
            }
            auto* matrix = new double[16];
            for (int r = 0; r < 4; ++r)
                for (int c = 0; c < 4; ++c) matrix[4 * r + c] = result.matrix(r, c);
            nb::capsule owner(matrix, [](void* p) noexcept { delete[] static_cast<double*>(p); });
            return nb::make_tuple(nb::ndarray<nb::numpy, double, nb::shape<4, 4>>(matrix, {4, 4}, owner),
                                  result.iterations, result.inlier_rms);
        },
        "fixed"_a, "face_normals"_a, "sample"_a, "prior"_a, "start"_a, "iterations"_a, "tukey_factor"_a,
        "min_scale"_a, "tolerance"_a,
        "(matrix (4, 4), iterations, inlier_rms) of a rigid point-to-plane ICP of sample onto fixed.");
}

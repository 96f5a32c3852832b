// The canonical array types shared by every kernel and the bindings.
#pragma once

#include <Eigen/Core>
#include <cstdint>

namespace tpscore {

/// Row-major matrices match C-contiguous NumPy arrays, so bindings never copy input.
using MatrixX = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
/// (n, 3) points, row-major: one point per row.
using Points = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;
/// (m, 3) triangles as vertex indices.
using Faces = Eigen::Matrix<std::int64_t, Eigen::Dynamic, 3, Eigen::RowMajor>;
using VectorX = Eigen::VectorXd;
using IndexVector = Eigen::Matrix<std::int64_t, Eigen::Dynamic, 1>;

using PointsRef = Eigen::Ref<const Points>;
using FacesRef = Eigen::Ref<const Faces>;
using MatrixRef = Eigen::Ref<const MatrixX>;

}  // namespace tpscore

// Rigid point-to-plane ICP (see tpscore/rigid_icp.hpp). The same steps as the NumPy
// reference (tpscore.reference.rigid), in one call: an alignment runs up to 30
// iterations, and the Python loop spent as long between closest-point queries as in
// them.
#include "tpscore/rigid_icp.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

namespace tpscore {

namespace {

// NumPy's median: the middle value, or the mean of the two middle values.
double median(std::vector<double>& values) {
    const std::size_t n = values.size();
    const std::size_t mid = n / 2;
    std::nth_element(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(mid), values.end());
    const double upper = values[mid];
    if (n % 2 == 1) return upper;
    const double lower = *std::max_element(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(mid));
    return (lower + upper) / 2.0;
}

// The rotation by the rotation vector v (Rodrigues' formula; the identity for v = 0).
Eigen::Matrix3d rotation_of(const Eigen::Vector3d& v) {
    const double angle = v.norm();
    if (angle == 0.0) return Eigen::Matrix3d::Identity();
    return Eigen::AngleAxisd(angle, v / angle).toRotationMatrix();
}

}  // namespace

RigidIcpResult rigid_icp(const MeshSurface& fixed, const double* face_normals, const PointsRef& sample,
                         const double* prior, const Eigen::Matrix4d& start, const RigidIcpSettings& settings,
                         int workers) {
    const auto m = static_cast<std::size_t>(sample.rows());
    RigidIcpResult result;
    result.matrix = start;
    result.inlier_rms = std::numeric_limits<double>::quiet_NaN();
    Points moved(sample.rows(), 3);
    std::vector<double> closest(3 * m), barycentric(3 * m), distances(m), weight(m), signed_distance(m);
    std::vector<std::int64_t> triangles(m);
    std::vector<double> scratch;
    scratch.reserve(m);
    bool any_prior = false;
    for (std::size_t i = 0; i < m; ++i) any_prior = any_prior || prior[i] > 0.5;
    for (int iteration = 1; iteration <= settings.iterations; ++iteration) {
        result.iterations = iteration;
        const Eigen::Matrix3d rotation = result.matrix.topLeftCorner<3, 3>();
        const Eigen::Vector3d translation = result.matrix.topRightCorner<3, 1>();
        for (std::size_t i = 0; i < m; ++i)
            moved.row(static_cast<Eigen::Index>(i)) =
                (rotation * sample.row(static_cast<Eigen::Index>(i)).transpose() + translation).transpose();
        fixed.closest_point(moved, closest.data(), triangles.data(), barycentric.data(), distances.data(), workers);

        scratch.clear();
        for (std::size_t i = 0; i < m; ++i)
            if (!any_prior || prior[i] > 0.5) scratch.push_back(distances[i]);
        const double scale = std::max(1.4826 * median(scratch), settings.min_scale);
        double weight_sum = 0.0;
        Eigen::Vector3d centre = Eigen::Vector3d::Zero();
        for (std::size_t i = 0; i < m; ++i) {
            const double u = distances[i] / (settings.tukey_factor * scale);
            weight[i] = (u < 1.0 ? (1.0 - u * u) * (1.0 - u * u) : 0.0) * prior[i];
            weight_sum += weight[i];
        }
        if (weight_sum < 6.0) break;
        for (std::size_t i = 0; i < m; ++i) centre += weight[i] * moved.row(static_cast<Eigen::Index>(i)).transpose();
        centre /= weight_sum;

        // Linearised point-to-plane step: rotation vector omega and translation t about
        // the centroid (which keeps the 6 x 6 normal equations well scaled).
        Eigen::Matrix<double, 6, 6> normal_matrix = 1e-9 * Eigen::Matrix<double, 6, 6>::Identity();
        Eigen::Matrix<double, 6, 1> rhs = Eigen::Matrix<double, 6, 1>::Zero();
        double squared_sum = 0.0;
        for (std::size_t i = 0; i < m; ++i) {
            const Eigen::Vector3d p = moved.row(static_cast<Eigen::Index>(i)).transpose();
            const Eigen::Vector3d n(face_normals + 3 * triangles[i]);
            const Eigen::Vector3d q(closest.data() + 3 * i);
            const double distance = (p - q).dot(n);
            signed_distance[i] = distance;
            Eigen::Matrix<double, 6, 1> row;
            row << (p - centre).cross(n), n;
            normal_matrix.noalias() += weight[i] * row * row.transpose();
            rhs.noalias() -= weight[i] * distance * row;
            squared_sum += weight[i] * distance * distance;
        }
        const Eigen::Matrix<double, 6, 1> step = normal_matrix.partialPivLu().solve(rhs);
        const Eigen::Matrix3d update_rotation = rotation_of(step.head<3>());
        Eigen::Matrix4d update = Eigen::Matrix4d::Identity();
        update.topLeftCorner<3, 3>() = update_rotation;
        update.topRightCorner<3, 1>() = centre + step.tail<3>() - update_rotation * centre;
        result.matrix = update * result.matrix;
        result.inlier_rms = std::sqrt(squared_sum / weight_sum);
        double motion = 0.0;
        const Eigen::Matrix3d change = update_rotation - Eigen::Matrix3d::Identity();
        for (std::size_t i = 0; i < m; ++i) {
            const Eigen::Vector3d shift =
                change * (moved.row(static_cast<Eigen::Index>(i)).transpose() - centre) + step.tail<3>();
            motion = std::max(motion, shift.cwiseAbs().maxCoeff());
        }
        if (motion < settings.tolerance) break;
    }
    return result;
}

}  // namespace tpscore

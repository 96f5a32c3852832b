// The registration's data terms (see tpscore/registration_terms.hpp).
#include "tpscore/registration_terms.hpp"

#include <algorithm>
#include <cmath>
#include <vector>

namespace tpscore {

namespace {

constexpr double kMadToSigma = 1.4826;
constexpr int kEntryRow[6] = {0, 0, 0, 1, 1, 2};
constexpr int kEntryColumn[6] = {0, 1, 2, 1, 2, 2};

// u . v in NumPy's einsum order (see the header).
inline double dot(const double* u, const double* v) {
    return ((0.0 + u[0] * v[0]) + u[2] * v[2]) + u[1] * v[1];
}

// numpy.median of the values (reordered in place): the middle one, or the mean of the
// two middle ones.
double median(std::vector<double>& values) {
    const std::size_t n = values.size();
    const auto upper = values.begin() + static_cast<std::ptrdiff_t>(n / 2);
    std::nth_element(values.begin(), upper, values.end());
    if (n % 2 == 1) return *upper;
    const double lower = *std::max_element(values.begin(), upper);
    return (lower + *upper) / 2.0;
}

// geometry.robust_scale: at least floor, floor alone without values.
double robust_scale(std::vector<double>& values, double floor) {
    if (values.empty()) return floor;
    return std::max(kMadToSigma * median(values), floor);
}

// geometry.tukey_weights of one residual, as NumPy computes (1 - u^2)^2.
inline double tukey(double residual, double cutoff) {
    const double u = std::abs(residual) / cutoff;
    if (!(u < 1.0)) return 0.0;
    const double v = 1.0 - u * u;
    return v * v;
}

}  // namespace

void point_to_plane_terms(std::int64_t m, const double* sample, const double* moved, const double* closest,
                          const double* distances, const double* normals, const double* prior, double floor,
                          double tukey_factor, double* blocks, double* rhs, double* along, double* weight) {
    std::vector<char> rim(static_cast<std::size_t>(m));
    std::vector<double> on_surface;
    on_surface.reserve(static_cast<std::size_t>(m));
    for (std::int64_t i = 0; i < m; ++i) {
        const double* n = normals + 3 * i;
        const double offset[3] = {moved[3 * i] - closest[3 * i], moved[3 * i + 1] - closest[3 * i + 1],
                                  moved[3 * i + 2] - closest[3 * i + 2]};
        along[i] = dot(offset, n);
        rim[i] = std::abs(along[i]) < 0.8 * distances[i] - 0.05;
        if (!rim[i]) on_surface.push_back(std::abs(distances[i]));
    }
    const double cutoff = tukey_factor * robust_scale(on_surface, floor);
    for (std::int64_t i = 0; i < m; ++i) {
        const double* n = normals + 3 * i;
        const double w = (rim[i] ? 0.0 : tukey(distances[i], cutoff)) * prior[i];
        weight[i] = w;
        for (int e = 0; e < 6; ++e) blocks[6 * i + e] = w * (n[kEntryRow[e]] * n[kEntryColumn[e]]);
        const double to_point[3] = {closest[3 * i] - sample[3 * i], closest[3 * i + 1] - sample[3 * i + 1],
                                    closest[3 * i + 2] - sample[3 * i + 2]};
        const double pull = w * dot(to_point, n);
        for (int k = 0; k < 3; ++k) rhs[3 * i + k] = n[k] * pull;
    }
}

void texture_pull_terms(std::int64_t m, const double* sample, const double* moved, const double* targets,
                        const double* normals, const double* prior, double floor, double tukey_factor,
                        double* blocks, double* rhs) {
    std::vector<double> residual(static_cast<std::size_t>(m));
    std::vector<double> used;
    used.reserve(static_cast<std::size_t>(m));
    for (std::int64_t i = 0; i < m; ++i) {
        const double* n = normals + 3 * i;
        double offset[3] = {moved[3 * i] - targets[3 * i], moved[3 * i + 1] - targets[3 * i + 1],
                            moved[3 * i + 2] - targets[3 * i + 2]};
        const double along = dot(offset, n);
        for (int k = 0; k < 3; ++k) offset[k] -= along * n[k];
        residual[i] = std::sqrt((offset[0] * offset[0] + offset[1] * offset[1]) + offset[2] * offset[2]);
        if (prior[i] > 0) used.push_back(std::abs(residual[i]));
    }
    const double cutoff = tukey_factor * robust_scale(used, floor);
    for (std::int64_t i = 0; i < m; ++i) {
        const double* n = normals + 3 * i;
        const double w = (prior[i] > 0 ? tukey(residual[i], cutoff) : 0.0) * prior[i];
        for (int e = 0; e < 6; ++e) {
            const double identity = kEntryRow[e] == kEntryColumn[e] ? 1.0 : 0.0;
            blocks[6 * i + e] = w * (identity - n[kEntryRow[e]] * n[kEntryColumn[e]]);
        }
        double to_target[3] = {targets[3 * i] - sample[3 * i], targets[3 * i + 1] - sample[3 * i + 1],
                               targets[3 * i + 2] - sample[3 * i + 2]};
        const double along = dot(to_target, n);
        for (int k = 0; k < 3; ++k) {
            to_target[k] -= along * n[k];
            rhs[3 * i + k] = w * to_target[k];
        }
    }
}

}  // namespace tpscore

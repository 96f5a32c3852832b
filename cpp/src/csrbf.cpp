#include "tpscore/csrbf.hpp"

#include <Eigen/Eigenvalues>
#include <Eigen/IterativeLinearSolvers>
#include <Eigen/QR>
#include <Eigen/SparseCore>
#include <algorithm>
#include <climits>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>

#include "tpscore/parallel.hpp"

namespace tpscore {

namespace {

using Vec3 = Eigen::Vector3d;
using SparseMatrix = Eigen::SparseMatrix<double, Eigen::RowMajor, int>;

// Rows per thread below which a loop stays on the calling thread; a row costs a
// radius search or a small least-squares fit, a few microseconds.
constexpr std::size_t kRowChunk = 1024;
// Two centres closer than this fraction of the support make two equal matrix rows.
constexpr double kDuplicateFraction = 1e-9;
// Pivot (relative to the largest) below which a local fit counts as rank deficient:
// the centres around p_j do not determine that many coefficients, and a fit forced
// through them would oscillate between the centres.
constexpr double kRankThreshold = 1e-6;
// Incomplete LU settings (drop entries below drop_tolerance times their row's norm,
// keep at most fill_factor times the row's nonzeros of the matrix in each factor
// row). Phi is diagonally strong (phi(0) = 1, off-diagonal terms fall off as
// (1 - r)^4), so a sparse factor already brings BiCGSTAB down to a few iterations
// (3 at 40,000 quasi-uniform centres with ~45 neighbours, 13 for uniformly random
// ones); Eigen's defaults (1e-12, 10) keep so much fill that factorising costs
// several times more than the iterations it saves. A factor with fill factor 1
// broke down on random centres, hence 2; the denser second setting is the fallback.
struct IluSettings {
    double drop_tolerance;
    int fill_factor;
};
constexpr IluSettings kIluSettings[] = {{1e-3, 2}, {1e-5, 6}};

// Eigen's incomplete LU, minus its fill-reducing (AMD) reordering: the unknowns
// are already in kd-tree order, which keeps the fill local, and AMD alone would
// cost about as much as the factorisation.
class OrderedIncompleteLUT : public Eigen::IncompleteLUT<double, int> {
public:
    template <class MatrixType>
    void analyzePattern(const MatrixType& matrix) {
        m_P.setIdentity(matrix.rows());
        m_Pinv.setIdentity(matrix.rows());
        m_analysisIsOk = true;
        m_factorizationIsOk = false;
        m_isInitialized = true;
    }
};

Vec3 row3(const Points& points, std::int64_t i) {
    return Vec3(points(i, 0), points(i, 1), points(i, 2));
}

// An orthonormal (t1, t2) with t1 x t2 = n, chosen deterministically from n.
void tangent_frame(const Vec3& n, Vec3& t1, Vec3& t2) {
    int axis = 0;  // the coordinate axis least aligned with n
    if (std::abs(n[1]) < std::abs(n[axis])) axis = 1;
    if (std::abs(n[2]) < std::abs(n[axis])) axis = 2;
    t1 = n.cross(Vec3::Unit(axis)).normalized();
    t2 = n.cross(t1);
}

// Runs BiCGSTAB on A x = b from x = 0, restarting from the current x while the true
// relative residual is above the tolerance and the iteration budget lasts (Eigen's
// recursively updated residual can drift from the true one). Returns iterations used
// and sets the true relative residual.
template <class Preconditioner>
std::int64_t solve_column(const SparseMatrix& a, const Preconditioner& preconditioner,
                          const VectorX& b, double tolerance, std::int64_t max_iterations,
                          VectorX& x, double& residual) {
    x.setZero(b.size());
    const double b_norm = b.norm();
    if (b_norm == 0) {
        residual = 0;
        return 0;
    }
    std::int64_t used = 0;
    residual = 1;
    // Each restart must make progress; a handful covers drift, more means stagnation.
    for (int restart = 0; restart < 4 && used < max_iterations; ++restart) {
        Eigen::Index iterations = max_iterations - used;
        double estimate = tolerance;
        Eigen::internal::bicgstab(a, b, x, preconditioner, iterations, estimate);
        used += iterations;
        residual = (b - a * x).norm() / b_norm;
        if (!std::isfinite(residual)) {
            residual = std::numeric_limits<double>::infinity();
            break;
        }
        if (residual <= tolerance || iterations == 0) break;
    }
    return used;
}

}  // namespace

CSRBF::CSRBF(const PointsRef& centres, const MatrixRef& values, const PointsRef& normals,
             const CSRBFOptions& options)
    : options_(options), centres_(centres), tree_(centres) {
    const std::int64_t n = centres_.rows();
    const std::int64_t k = values.cols();
    const double sigma = options_.support;

    // The system is set up in the kd-tree's leaf order ("solve order"): neighbours in
    // space are neighbours in the matrix, which keeps the products with Phi cache
    // friendly and lets the incomplete LU work without a fill-reducing reordering.
    // Results are mapped back to the caller's order at the end.
    const std::vector<std::int64_t>& order = tree_.order();  // solve row -> caller row
    std::vector<std::int64_t> rank(static_cast<std::size_t>(n));  // caller row -> solve row
    for (std::int64_t r = 0; r < n; ++r) rank[static_cast<std::size_t>(order[static_cast<std::size_t>(r)])] = r;
    const Points& ordered = tree_.permuted_points();

    // 1. Neighbours within the support. Phi is symmetric, so scattering the rows of
    //    the radius query into the rows of its transpose, in row order, gives every
    //    row's columns already sorted (a counting sort, no comparisons).
    RadiusNeighbours found = tree_.query_radius(ordered, sigma, false);
    const IndexVector& query_offsets = found.offsets;
    IndexVector& query_neighbours = found.indices;
    VectorX& query_distances = found.distances;
    std::vector<std::int64_t> offsets(static_cast<std::size_t>(n) + 1, 0);
    for (const std::int64_t j : query_neighbours) ++offsets[static_cast<std::size_t>(rank[static_cast<std::size_t>(j)]) + 1];
    for (std::size_t r = 0; r < static_cast<std::size_t>(n); ++r) offsets[r + 1] += offsets[r];
    const auto total = static_cast<std::size_t>(offsets.back());
    std::vector<std::int64_t> columns(total);
    std::vector<double> distances(total);
    {
        std::vector<std::int64_t> cursor(offsets.begin(), offsets.end() - 1);
        for (std::size_t r = 0; r < static_cast<std::size_t>(n); ++r) {
            const auto row_index = static_cast<Eigen::Index>(r);
            for (Eigen::Index e = query_offsets[row_index]; e < query_offsets[row_index + 1]; ++e) {
                const auto row = static_cast<std::size_t>(rank[static_cast<std::size_t>(query_neighbours[e])]);
                const auto slot = static_cast<std::size_t>(cursor[row]++);
                columns[slot] = static_cast<std::int64_t>(r);
                distances[slot] = query_distances[e];
            }
        }
    }
    query_neighbours.resize(0);
    query_distances.resize(0);

    // Coincident centres make two equal rows; report the pair with the smallest
    // caller indices so the message does not depend on the tree.
    std::int64_t duplicate_i = -1, duplicate_j = -1;
    for (std::size_t r = 0; r < static_cast<std::size_t>(n); ++r) {
        for (auto e = static_cast<std::size_t>(offsets[r]); e < static_cast<std::size_t>(offsets[r + 1]); ++e) {
            if (columns[e] == static_cast<std::int64_t>(r) || distances[e] > kDuplicateFraction * sigma) continue;
            const std::int64_t a = order[r], b = order[static_cast<std::size_t>(columns[e])];
            const std::int64_t i = std::min(a, b), j = std::max(a, b);
            if (duplicate_i < 0 || std::make_pair(i, j) < std::make_pair(duplicate_i, duplicate_j)) {
                duplicate_i = i;
                duplicate_j = j;
            }
        }
    }
    if (duplicate_i >= 0)
        throw std::invalid_argument(
            "centres contains duplicate points: rows " + std::to_string(duplicate_i) + " and " +
            std::to_string(duplicate_j) + " coincide (closer than 1e-9 times the support); "
            "remove or merge duplicates");

    // 2. Local models, stored in the caller's order.
    if (options_.quadric) {
        normals_.resize(n, 3);
        tangent_u_.resize(n, 3);
        tangent_v_.resize(n, 3);
        local_models_.setZero(n, 6 * k);
        orders_.resize(n);
        parallel_for(static_cast<std::size_t>(n), kRowChunk / 4, [&](std::size_t begin, std::size_t end) {
            Eigen::MatrixXd design, rhs;
            for (std::size_t r = begin; r < end; ++r) {
                const std::int64_t j = order[r];  // caller index of this centre
                const auto first = static_cast<std::size_t>(offsets[r]);
                const auto last = static_cast<std::size_t>(offsets[r + 1]);
                const auto count = static_cast<Eigen::Index>(last - first);
                const Vec3 pj = row3(centres_, j);
                Vec3 normal;
                if (normals.rows() > 0) {
                    normal = Vec3(normals(j, 0), normals(j, 1), normals(j, 2)).normalized();
                } else {
                    // Weighted PCA: the normal is the direction of least spread.
                    Vec3 mean = Vec3::Zero();
                    double total_weight = 0;
                    for (std::size_t e = first; e < last; ++e) {
                        const double w = wendland(distances[e] / sigma);
                        mean += w * row3(ordered, columns[e]);
                        total_weight += w;
                    }
                    mean /= total_weight;  // >= phi(0) = 1: the centre itself
                    Eigen::Matrix3d covariance = Eigen::Matrix3d::Zero();
                    for (std::size_t e = first; e < last; ++e) {
                        const double w = wendland(distances[e] / sigma);
                        const Vec3 d = row3(ordered, columns[e]) - mean;
                        covariance += w * d * d.transpose();
                    }
                    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eigen(covariance);
                    normal = eigen.eigenvectors().col(0);  // eigenvalues ascending
                }
                Vec3 t1, t2;
                tangent_frame(normal, t1, t2);
                normals_.row(j) = normal;
                tangent_u_.row(j) = t1;
                tangent_v_.row(j) = t2;

                // Rows sqrt(w) [1, u, v, u^2, 2uv, v^2] in (u, v) / sigma, so every
                // column is O(1) and the pivots of different orders compare.
                design.resize(count, 6);
                rhs.resize(count, k);
                for (std::size_t e = first; e < last; ++e) {
                    const std::int64_t i = order[static_cast<std::size_t>(columns[e])];
                    const double w = std::sqrt(wendland(distances[e] / sigma));
                    const Vec3 d = (row3(centres_, i) - pj) / sigma;
                    const double u = d.dot(t1), v = d.dot(t2);
                    const auto row = static_cast<Eigen::Index>(e - first);
                    design.row(row) << w, w * u, w * v, w * u * u, w * 2 * u * v, w * v * v;
                    rhs.row(row) = w * values.row(i);
                }
                std::int64_t model_order = 0;
                Eigen::MatrixXd solution;
                for (const int terms : {6, 3}) {
                    if (count < terms) continue;
                    Eigen::ColPivHouseholderQR<Eigen::MatrixXd> qr(design.leftCols(terms));
                    qr.setThreshold(kRankThreshold);
                    if (qr.rank() < terms) continue;
                    solution = qr.solve(rhs);
                    model_order = terms == 6 ? 2 : 1;
                    break;
                }
                if (model_order == 0) {
                    // The weighted mean: always defined, p_j itself has weight 1.
                    solution = (design.col(0).transpose() * rhs) / design.col(0).squaredNorm();
                }
                orders_[j] = model_order;
                for (std::int64_t c = 0; c < k; ++c)
                    for (Eigen::Index t = 0; t < solution.rows(); ++t)
                        local_models_(j, 6 * c + t) = solution(t, c);
            }
        });
    } else {
        normals_.resize(0, 3);
        orders_.setConstant(n, -1);
    }

    // 3. The matrix, written straight into Eigen's compressed row-major storage, and
    //    the right-hand sides, both in solve order.
    nnz_ = static_cast<std::int64_t>(total);
    if (nnz_ > INT_MAX) throw std::length_error("CSRBF matrix has more than 2^31 entries; use a smaller support");
    SparseMatrix phi(n, n);
    phi.resizeNonZeros(static_cast<Eigen::Index>(nnz_));
    for (std::size_t r = 0; r <= static_cast<std::size_t>(n); ++r) phi.outerIndexPtr()[r] = static_cast<int>(offsets[r]);
    MatrixX rhs(n, k);
    parallel_for(static_cast<std::size_t>(n), kRowChunk, [&](std::size_t begin, std::size_t end) {
        std::vector<double> local(static_cast<std::size_t>(k));
        for (std::size_t r = begin; r < end; ++r) {
            const std::int64_t i = order[r];
            std::fill(local.begin(), local.end(), 0.0);
            const double pi[3] = {centres_(i, 0), centres_(i, 1), centres_(i, 2)};
            for (auto e = static_cast<std::size_t>(offsets[r]); e < static_cast<std::size_t>(offsets[r + 1]); ++e) {
                const double value = wendland(distances[e] / sigma);
                const bool diagonal = columns[e] == static_cast<std::int64_t>(r);
                phi.innerIndexPtr()[e] = static_cast<int>(columns[e]);
                phi.valuePtr()[e] = value + (diagonal ? options_.smoothing : 0.0);
                if (options_.quadric) add_local_model(order[static_cast<std::size_t>(columns[e])], pi, value, local.data());
            }
            for (std::int64_t c = 0; c < k; ++c) rhs(static_cast<std::int64_t>(r), c) = values(i, c) - local[static_cast<std::size_t>(c)];
        }
    });

    // 4. Solve each column; the preconditioner is computed once and shared (its
    //    solve is const), the columns run in parallel.
    // Until a solve says otherwise (e.g. every incomplete LU broke down): not converged.
    coefficients_.setZero(n, k);
    iterations_.setZero(k);
    residuals_.setConstant(k, std::numeric_limits<double>::infinity());
    converged_.setConstant(k, false);
    auto solve_all = [&](const auto& preconditioner) {
        parallel_for(static_cast<std::size_t>(k), 1, [&](std::size_t begin, std::size_t end) {
            VectorX x, b;
            for (std::size_t cu = begin; cu < end; ++cu) {
                const auto c = static_cast<Eigen::Index>(cu);
                b = rhs.col(c);
                double residual = 0;
                iterations_[c] = solve_column(phi, preconditioner, b, options_.tolerance,
                                              options_.max_iterations, x, residual);
                residuals_[c] = residual;
                converged_[c] = residual <= options_.tolerance;
                for (std::int64_t r = 0; r < n; ++r) coefficients_(order[static_cast<std::size_t>(r)], c) = x[r];
            }
        });
    };
    if (options_.preconditioner == CSRBFPreconditioner::ilu) {
        // A sparse factor first; if it breaks down or a column does not converge
        // (strongly clustered centres), once more with a denser one.
        for (const IluSettings& settings : kIluSettings) {
            OrderedIncompleteLUT ilu;
            ilu.setDroptol(settings.drop_tolerance);
            ilu.setFillfactor(settings.fill_factor);
            // Not compute(): it would call the base class's analyzePattern.
            ilu.analyzePattern(phi);
            ilu.factorize(phi);
            if (ilu.info() != Eigen::Success) continue;
            solve_all(ilu);
            if (converged_.all()) break;
        }
    } else {
        Eigen::DiagonalPreconditioner<double> diagonal;
        diagonal.compute(phi);
        solve_all(diagonal);
    }
}

void CSRBF::add_local_model(std::int64_t j, const double* x, double weight, double* out) const {
    const double sigma = options_.support;
    const double d[3] = {(x[0] - centres_(j, 0)) / sigma, (x[1] - centres_(j, 1)) / sigma,
                         (x[2] - centres_(j, 2)) / sigma};
    const double u = d[0] * tangent_u_(j, 0) + d[1] * tangent_u_(j, 1) + d[2] * tangent_u_(j, 2);
    const double v = d[0] * tangent_v_(j, 0) + d[1] * tangent_v_(j, 1) + d[2] * tangent_v_(j, 2);
    const double basis[6] = {1.0, u, v, u * u, 2 * u * v, v * v};
    const std::int64_t k = local_models_.cols() / 6;
    const double* model = local_models_.data() + j * local_models_.cols();
    for (std::int64_t c = 0; c < k; ++c) {
        double g = 0;
        for (int t = 0; t < 6; ++t) g += model[6 * c + t] * basis[t];
        out[c] += weight * g;
    }
}

MatrixX CSRBF::evaluate(const PointsRef& queries) const {
    const std::int64_t m = queries.rows();
    const std::int64_t k = coefficients_.cols();
    const double sigma = options_.support;
    MatrixX result(m, k);
    parallel_for(static_cast<std::size_t>(m), kRowChunk, [&](std::size_t begin, std::size_t end) {
        std::vector<std::pair<std::int64_t, double>> found;
        std::vector<double> sum(static_cast<std::size_t>(k));
        for (std::size_t qu = begin; qu < end; ++qu) {
            const auto q = static_cast<std::int64_t>(qu);
            const double x[3] = {queries(q, 0), queries(q, 1), queries(q, 2)};
            found.clear();
            tree_.radius_search(x, sigma, found);
            std::fill(sum.begin(), sum.end(), 0.0);
            for (const auto& [j, d2] : found) {
                const double weight = wendland(std::sqrt(d2) / sigma);
                if (weight == 0) continue;
                for (std::int64_t c = 0; c < k; ++c)
                    sum[static_cast<std::size_t>(c)] += coefficients_(j, c) * weight;
                if (options_.quadric) add_local_model(j, x, weight, sum.data());
            }
            for (std::int64_t c = 0; c < k; ++c) result(q, c) = sum[static_cast<std::size_t>(c)];
        }
    });
    return result;
}

}  // namespace tpscore

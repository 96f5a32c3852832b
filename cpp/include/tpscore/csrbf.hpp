// Compactly supported radial basis functions (CSRBF) with Wendland's kernel and
// optional local quadrics, solved as a sparse system by preconditioned BiCGSTAB.
//
// The field, for centres p_j, support sigma and phi_sigma(d) = phi(d / sigma),
//   f(x) = sum_j (g_j(x) + c_j) phi_sigma(|x - p_j|),
// with phi(r) = (1 - r)^4_+ (4 r + 1) (Wendland's C2 function, positive definite in
// 3D) and g_j a local model of the values around p_j (zero without the quadric).
// It is the vector-valued form of the implicit-surface CSRBF of Ohtake, Belyaev and
// Seidel: each of the k value columns is fitted independently with the same matrix.
#pragma once

#include <cstdint>
#include <vector>

#include "tpscore/kdtree.hpp"
#include "tpscore/types.hpp"

namespace tpscore {

/// Wendland's phi(r) = (1 - r)^4 (4 r + 1) for r < 1, else 0. phi(0) = 1.
inline double wendland(double r) {
    if (r >= 1.0) return 0.0;
    const double t = 1.0 - r;
    const double t2 = t * t;
    return t2 * t2 * (4.0 * r + 1.0);
}

/// Preconditioner of the BiCGSTAB solve.
enum class CSRBFPreconditioner : int {
    diagonal = 0,  ///< Jacobi (Eigen::DiagonalPreconditioner)
    ilu = 1,       ///< incomplete LU with threshold (Eigen::IncompleteLUT)
};

struct CSRBFOptions {
    double support = 1.0;    ///< sigma > 0, in the units of the centres
    double smoothing = 0.0;  ///< >= 0, added to the diagonal of the matrix
    bool quadric = false;    ///< fit the local models g_j (else g_j = 0)
    CSRBFPreconditioner preconditioner = CSRBFPreconditioner::ilu;
    double tolerance = 1e-10;      ///< > 0, relative residual |b - A c| / |b| to reach
    std::int64_t max_iterations = 1000;  ///< >= 1, BiCGSTAB iterations per column
};

/// A fitted CSRBF field; immutable after construction, so several threads may
/// evaluate it at once.
///
/// Fitting, in order:
/// 1. neighbours: every pair of centres closer than sigma, from a kd-tree radius
///    search; two centres closer than 1e-9 sigma throw std::invalid_argument naming
///    both rows (the matrix would be singular).
/// 2. with the quadric, per centre j: a unit normal n_j (given, or the direction of
///    least spread of the Wendland-weighted neighbours: weighted PCA), a tangent frame
///    (t1, t2) orthogonal to it, and the Wendland-weighted least-squares fit of
///    g_j(x) = a + b u + c v + A u^2 + 2 B u v + C v^2, (u, v) = (x - p_j).(t1, t2),
///    to the values of the centres within sigma of p_j. A quadratic needs 6 such
///    centres (p_j included) in general position, a linear model 3; with fewer, or
///    when the weighted design matrix is rank deficient (pivot below 1e-6 of the
///    largest), the fit falls back to linear, then to a constant (the weighted mean).
/// 3. the sparse symmetric matrix Phi_ij = phi_sigma(|p_i - p_j|) + smoothing delta_ij
///    and the right-hand sides b_i = values_i - sum_j g_j(p_i) phi_sigma(|p_i - p_j|);
/// 4. per value column (columns in parallel), BiCGSTAB on Phi c = b with the chosen
///    preconditioner, from c = 0, restarted from the current c while the true relative
///    residual |b - Phi c| / |b| exceeds the tolerance and iterations remain. The
///    unknowns are ordered along the kd-tree's leaves (spatially coherent), and the
///    incomplete LU uses that order instead of a fill-reducing one; if the sparse
///    factor breaks down or a column does not converge, the solve is repeated once
///    with a denser factor (iterations and residuals then report that attempt).
/// Non-convergence does not throw: converged() says which columns failed.
/// Without smoothing f interpolates: f(p_i) = values_i up to the solver tolerance.
class CSRBF {
public:
    /// Preconditions: centres (n, 3) finite, n >= 1; values (n, k) finite, k >= 1;
    /// normals (n, 3) finite and nonzero, or 0 rows to estimate them (used only with
    /// the quadric); options valid as documented in CSRBFOptions.
    CSRBF(const PointsRef& centres, const MatrixRef& values, const PointsRef& normals,
          const CSRBFOptions& options);

    /// The field at each row of `queries` (m, 3): (m, k). Threaded over query rows;
    /// the result does not depend on the thread count. 0 farther than sigma from
    /// every centre.
    MatrixX evaluate(const PointsRef& queries) const;

    std::int64_t size() const { return centres_.rows(); }
    std::int64_t value_columns() const { return coefficients_.cols(); }
    /// (n, k) the c_j.
    const MatrixX& coefficients() const { return coefficients_; }
    /// (k,) BiCGSTAB iterations spent on each column (summed over restarts).
    const IndexVector& iterations() const { return iterations_; }
    /// (k,) true relative residual |b - Phi c| / |b| of each column (0 if b = 0).
    const VectorX& residuals() const { return residuals_; }
    /// (k,) whether each column reached the tolerance (residual finite and <= tolerance).
    const Eigen::Matrix<bool, Eigen::Dynamic, 1>& converged() const { return converged_; }
    /// Stored entries of Phi (including the diagonal).
    std::int64_t nnz() const { return nnz_; }
    /// (n,) order of each local model: 2 quadratic, 1 linear, 0 constant; -1 without
    /// the quadric.
    const IndexVector& quadric_orders() const { return orders_; }
    /// (n, 3) unit normals of the tangent frames (given or estimated); 0 rows without
    /// the quadric.
    const Points& normals() const { return normals_; }
    const CSRBFOptions& options() const { return options_; }

private:
    /// g_j at x (k values added to out[0..k)).
    void add_local_model(std::int64_t j, const double* x, double weight, double* out) const;

    CSRBFOptions options_;
    Points centres_;
    KDTree tree_;
    MatrixX coefficients_;   // (n, k)
    Points normals_;         // (n, 3) or (0, 3)
    Points tangent_u_;       // (n, 3) or (0, 3)
    Points tangent_v_;       // (n, 3) or (0, 3)
    MatrixX local_models_;   // (n, 6 k): per column (a, b, c, A, B, C) in (u, v) / sigma
    IndexVector orders_;
    IndexVector iterations_;
    VectorX residuals_;
    Eigen::Matrix<bool, Eigen::Dynamic, 1> converged_;
    std::int64_t nnz_ = 0;
};

}  // namespace tpscore

// Dense radial basis function interpolation with an affine part: the thin-plate
// spline of the expression-transfer pipeline and its relatives.
//
//   f(x) = [1 x y z] A + sum_i W_i phi(|x - p_i|),   with P^T W = 0,
//
// where P = [1 x y z] over the centres p_i. Fitting solves the saddle-point system
//
//   [ K + sign * lambda I   P ] [W]   [values]
//   [ P^T                   0 ] [A] = [  0   ]
//
// with K_ij = phi(|p_i - p_j|) and sign the kernel's definiteness sign (below), so
// that a larger lambda >= 0 always means a smoother, less exactly interpolating f.
#pragma once

#include <Eigen/Core>
#include <cstdint>

#include "tpscore/types.hpp"

namespace tpscore {

/// The radial functions phi(r), r in mm. Names are explicit because users confuse them.
enum class RbfKernel : int {
    /// phi(r) = r^2 ln r^2, phi(0) = 0: the 3D thin-plate spline of the pipeline
    /// (SciPy's `thin_plate_spline` is r^2 ln r = phi / 2: the same interpolant).
    /// Conditionally positive definite of order 2; smoothing sign +1.
    tps = 0,
    /// phi(r) = r: the 3D biharmonic Green's function (SciPy's `linear` is -r).
    /// Conditionally negative definite of order 1; smoothing sign -1 (K - lambda I).
    biharmonic = 1,
    /// phi(r) = r^3 (SciPy's `cubic`, same sign). Order 2; smoothing sign +1.
    triharmonic = 2,
    /// phi(r) = +sqrt(1 + (epsilon r)^2), Hardy's sign (SciPy's is -sqrt: the same
    /// interpolant with negated weights). Conditionally negative definite of order 1;
    /// smoothing sign -1.
    multiquadric = 3,
    /// phi(r) = exp(-(epsilon r)^2). Positive definite; smoothing sign +1.
    gaussian = 4,
};

/// +1 or -1: the sign that makes `sign * K` conditionally positive definite, used
/// for the smoothing term (K + sign * lambda I).
int rbf_smoothing_sign(RbfKernel kernel);

/// A fitted RBF. Immutable after rbf_fit, so any number of threads may evaluate it
/// at once.
///
/// The system is solved in normalised coordinates x' = (x - shift) / scale (centres
/// inside the unit ball), where the kernel matrix is well scaled; `weights`,
/// `affine` and `bending_energy` are mapped back to the original coordinates.
struct RbfModel {
    RbfKernel kernel = RbfKernel::tps;
    /// Shape parameter in 1/mm (gaussian, multiquadric); 0 for the other kernels.
    double epsilon = 0.0;
    /// lambda >= 0, in the units of phi (mm^2 for tps, mm for biharmonic, ...).
    double smoothing = 0.0;
    /// (n, 3) centres in mm, as given.
    Points centres;
    /// (n, k) radial weights W in original coordinates (units: values / phi).
    MatrixX weights;
    /// (4, k) affine part A in original coordinates: rows constant, x, y, z.
    MatrixX affine;
    /// trace(W^T K W), K the kernel matrix of the centres in original coordinates
    /// without the smoothing term. For tps and triharmonic it is >= 0 and proportional
    /// to the bending energy the spline minimises; for biharmonic and multiquadric
    /// it is <= 0 (their kernels are conditionally negative definite).
    double bending_energy = 0.0;
    /// An estimate of the reciprocal of the 1-norm condition number of the saddle-point
    /// matrix that was solved (normalised coordinates, polynomial rows and columns
    /// scaled to the kernel block): Hager and Higham's estimator of ||S^{-1}||_1.
    double rcond = 0.0;

    // --- the normalised form that evaluation uses --------------------------------
    Eigen::RowVector3d shift = Eigen::RowVector3d::Zero();
    double scale = 1.0;
    /// epsilon * scale: the shape parameter in normalised units.
    double epsilon_normalised = 0.0;
    /// Centre coordinates in normalised units, one array per axis (n each), so the
    /// evaluation loop reads them contiguously.
    Eigen::VectorXd centre_x, centre_y, centre_z;
    /// (n, k) column-major normalised weights: column c contiguous for the inner loop.
    Eigen::MatrixXd weights_normalised;
    /// (4, k) affine part in normalised coordinates.
    Eigen::MatrixXd affine_normalised;
    /// (4, 3) affine part of f(x) - x in normalised coordinates (k == 3 only), so
    /// the displacement never subtracts two large coordinates.
    Eigen::MatrixXd displacement_affine_normalised;

    std::int64_t size() const { return centres.rows(); }
    std::int64_t value_dim() const { return weights.cols(); }
};

/// Fits f with f(p_i) = values_i (exactly when smoothing == 0).
///
/// Solves by the null-space method with a Cholesky factorisation (see rbf.cpp);
/// threaded, and the result does not depend on the thread count.
///
/// centres (n, 3) finite, values (n, k) finite, k >= 1. epsilon > 0 for gaussian and
/// multiquadric (ignored otherwise), smoothing >= 0. The caller checks the geometry
/// (n >= 5, no coincident centres, centres not coplanar); whatever gets through,
/// a singular or non-finite system throws std::domain_error rather than returning
/// NaN. Bad sizes or parameters throw std::invalid_argument.
RbfModel rbf_fit(const PointsRef& centres, const MatrixRef& values, RbfKernel kernel,
                 double epsilon, double smoothing);

/// Writes f at each row of `queries` (m, 3) into `out` (m, k). With `displacement`,
/// writes f(x) - x instead (requires k == 3). Forms no (m, n) temporary; threaded
/// over blocks of query rows; the result does not depend on the thread count.
/// The caller allocates `out` (Python passes a NumPy array: see the binding).
/// Returns the first row whose value is not finite (it overflowed: a query far from
/// the centres), or -1; checked as the rows are written, while they are in cache.
std::int64_t rbf_evaluate(const RbfModel& model, const PointsRef& queries, bool displacement,
                          Eigen::Ref<MatrixX> out);

/// As above, returning a new (m, k) matrix.
MatrixX rbf_evaluate(const RbfModel& model, const PointsRef& queries, bool displacement);

/// The (m, n + 4) evaluation matrix E = [phi(|x - p_j|) | 1 x y z] in original
/// coordinates, so that E * [weights; affine] = f(x). Threaded over rows.
MatrixX rbf_evaluation_matrix(const RbfModel& model, const PointsRef& queries);

}  // namespace tpscore

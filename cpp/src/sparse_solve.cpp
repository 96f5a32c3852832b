// Sparse direct solve (see tpscore/sparse_solve.hpp).
#include "tpscore/sparse_solve.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <tuple>
#include <utility>

#include "tpscore/parallel.hpp"

namespace tpscore {

namespace {

using Matrix = Eigen::SparseMatrix<double, Eigen::ColMajor, int>;
using Ldlt = Eigen::SimplicialLDLT<Matrix, Eigen::Lower, Eigen::AMDOrdering<int>>;

// The lower triangle as an Eigen matrix, filled in its compressed storage directly:
// the caller hands over sorted CSC arrays, so going through triplets would only sort
// them again. values may be null (a pattern; the values are zero).
Matrix lower_from_csc(std::int64_t n, const std::int64_t* indptr, const std::int64_t* indices,
                      const double* values) {
    const std::int64_t nnz = indptr[n];
    Matrix lower(static_cast<Eigen::Index>(n), static_cast<Eigen::Index>(n));
    lower.resizeNonZeros(static_cast<Eigen::Index>(nnz));
    int* outer = lower.outerIndexPtr();
    for (std::int64_t j = 0; j <= n; ++j) outer[j] = static_cast<int>(indptr[j]);
    int* inner = lower.innerIndexPtr();
    double* data = lower.valuePtr();
    for (std::int64_t k = 0; k < nnz; ++k) {
        inner[k] = static_cast<int>(indices[k]);
        data[k] = values ? values[k] : 0.0;
    }
    lower.finalize();
    return lower;
}

// Throws unless the factorisation succeeded with every pivot of D clearly positive;
// returns the (smallest, largest) pivot.
std::pair<double, double> checked_pivots(const Ldlt& ldlt, std::int64_t n,
                                         double pivot_tolerance) {
    if (ldlt.info() != Eigen::Success)
        throw std::invalid_argument(
            "matrix is singular: its LDL^T factorisation met an exactly zero pivot");
    if (n == 0) return {0.0, 0.0};
    const Eigen::VectorXd& pivots = ldlt.vectorD();
    const double min_pivot = pivots.minCoeff();
    const double max_pivot = pivots.maxCoeff();
    const double scale = pivots.cwiseAbs().maxCoeff();
    if (!(min_pivot > pivot_tolerance * scale)) {
        std::ostringstream message;
        message.precision(3);
        message << "matrix is not positive definite: the smallest pivot of its LDL^T "
                   "factorisation is "
                << min_pivot << " against a largest |pivot| of " << scale
                << " (it is singular or indefinite)";
        throw std::invalid_argument(message.str());
    }
    return {min_pivot, max_pivot};
}

// Solves column by column, in parallel. One column costs two triangular sweeps over
// the factor (O(nnz(L))). Below a few thousand unknowns a column takes microseconds,
// less than starting a thread, so small systems take several columns per chunk.
// Columns never share state, so the result does not depend on how they are split.
Eigen::MatrixXd solve_columns(const Ldlt& ldlt, std::int64_t n,
                              const Eigen::Ref<const Eigen::MatrixXd>& rhs) {
    Eigen::MatrixXd solution(rhs.rows(), rhs.cols());
    const std::size_t columns = static_cast<std::size_t>(rhs.cols());
    const std::size_t min_chunk =
        n >= 2000 ? 1 : static_cast<std::size_t>(2000 / std::max<std::int64_t>(n, 1));
    auto body = [&](std::size_t begin, std::size_t end) {
        const Eigen::Index b = static_cast<Eigen::Index>(begin);
        const Eigen::Index count = static_cast<Eigen::Index>(end - begin);
        solution.middleCols(b, count) = ldlt.solve(rhs.middleCols(b, count));
    };
    parallel_for(columns, min_chunk, body);
    return solution;
}

}  // namespace

SparseCholesky::SparseCholesky(std::int64_t n, const std::int64_t* indptr,
                               const std::int64_t* indices, const double* values,
                               double pivot_tolerance)
    : n_(n) {
    ldlt_.compute(lower_from_csc(n, indptr, indices, values));
    std::tie(min_pivot_, max_pivot_) = checked_pivots(ldlt_, n, pivot_tolerance);
}

Eigen::MatrixXd SparseCholesky::solve(const Eigen::Ref<const Eigen::MatrixXd>& rhs) const {
    return solve_columns(ldlt_, n_, rhs);
}

std::int64_t SparseCholesky::factor_nonzeros() const {
    return static_cast<std::int64_t>(ldlt_.matrixL().nestedExpression().nonZeros());
}

PatternCholesky::PatternCholesky(std::int64_t n, const std::int64_t* indptr,
                                 const std::int64_t* indices)
    : n_(n), lower_(lower_from_csc(n, indptr, indices, nullptr)) {
    ldlt_.analyzePattern(lower_);
}

void PatternCholesky::factorize(const double* values, double pivot_tolerance) {
    factorised_ = false;
    std::copy(values, values + lower_.nonZeros(), lower_.valuePtr());
    ldlt_.factorize(lower_);
    std::tie(min_pivot_, max_pivot_) = checked_pivots(ldlt_, n_, pivot_tolerance);
    factorised_ = true;
}

Eigen::MatrixXd PatternCholesky::solve(const Eigen::Ref<const Eigen::MatrixXd>& rhs) const {
    if (!factorised_) throw std::logic_error("no factor: factorize() has not succeeded");
    return solve_columns(ldlt_, n_, rhs);
}

}  // namespace tpscore

// Sparse direct solve (see tpscore/sparse_solve.hpp).
#include "tpscore/sparse_solve.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "tpscore/parallel.hpp"

namespace tpscore {

SparseCholesky::SparseCholesky(std::int64_t n, const std::int64_t* indptr,
                               const std::int64_t* indices, const double* values,
                               double pivot_tolerance)
    : n_(n) {
    const std::int64_t nnz = indptr[n];
    Matrix lower(static_cast<Eigen::Index>(n), static_cast<Eigen::Index>(n));
    // Fill the compressed storage directly: the caller hands over sorted CSC arrays,
    // so going through triplets would only sort them again.
    lower.resizeNonZeros(static_cast<Eigen::Index>(nnz));
    int* outer = lower.outerIndexPtr();
    for (std::int64_t j = 0; j <= n; ++j) outer[j] = static_cast<int>(indptr[j]);
    int* inner = lower.innerIndexPtr();
    double* data = lower.valuePtr();
    for (std::int64_t k = 0; k < nnz; ++k) {
        inner[k] = static_cast<int>(indices[k]);
        data[k] = values[k];
    }
    lower.finalize();

    ldlt_.compute(lower);
    if (ldlt_.info() != Eigen::Success)
        throw std::invalid_argument(
            "matrix is singular: its LDL^T factorisation met an exactly zero pivot");
    const Eigen::VectorXd& pivots = ldlt_.vectorD();
    if (n > 0) {
        min_pivot_ = pivots.minCoeff();
        max_pivot_ = pivots.maxCoeff();
        const double scale = pivots.cwiseAbs().maxCoeff();
        if (!(min_pivot_ > pivot_tolerance * scale)) {
            std::ostringstream message;
            message.precision(3);
            message << "matrix is not positive definite: the smallest pivot of its LDL^T "
                       "factorisation is "
                    << min_pivot_ << " against a largest |pivot| of " << scale
                    << " (it is singular or indefinite)";
            throw std::invalid_argument(message.str());
        }
    }
}

Eigen::MatrixXd SparseCholesky::solve(const Eigen::Ref<const Eigen::MatrixXd>& rhs) const {
    Eigen::MatrixXd solution(rhs.rows(), rhs.cols());
    const std::size_t columns = static_cast<std::size_t>(rhs.cols());
    // One column costs two triangular sweeps over the factor (O(nnz(L))). Below a few
    // thousand unknowns a column takes microseconds, less than starting a thread, so
    // small systems take several columns per chunk. Columns never share state, so the
    // result does not depend on how they are split.
    const std::size_t min_chunk =
        n_ >= 2000 ? 1 : static_cast<std::size_t>(2000 / std::max<std::int64_t>(n_, 1));
    auto body = [&](std::size_t begin, std::size_t end) {
        const Eigen::Index b = static_cast<Eigen::Index>(begin);
        const Eigen::Index count = static_cast<Eigen::Index>(end - begin);
        solution.middleCols(b, count) = ldlt_.solve(rhs.middleCols(b, count));
    };
    parallel_for(columns, min_chunk, body);
    return solution;
}

std::int64_t SparseCholesky::factor_nonzeros() const {
    return static_cast<std::int64_t>(ldlt_.matrixL().nestedExpression().nonZeros());
}

}  // namespace tpscore

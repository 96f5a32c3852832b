// Sparse direct solve of symmetric positive-definite systems: factorise once, solve
// for many right-hand sides.
#pragma once

#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <cstdint>

#include "tpscore/types.hpp"

namespace tpscore {

/// A sparse symmetric positive-definite matrix factorised as P A P^T = L D L^T
/// (Eigen's SimplicialLDLT with an approximate-minimum-degree ordering P).
///
/// The factor is immutable after construction, so solve() may be called from several
/// threads at once.
class SparseCholesky {
public:
    /// Factorises the n x n matrix whose LOWER triangle (diagonal included) is given in
    /// compressed-sparse-column form: column j holds the row indices
    /// indices[indptr[j] .. indptr[j+1]) (all >= j, sorted, no duplicates) and the values
    /// at the same positions. Entries above the diagonal are never read.
    ///
    /// Preconditions (checked by the caller): indptr has n + 1 entries, indptr[0] = 0,
    /// nondecreasing; 0 <= indices < n; values finite; nnz < 2^31.
    /// Throws std::invalid_argument when a pivot of D is not positive beyond rounding
    /// (pivot <= pivot_tolerance * max |pivot|): the matrix is singular or indefinite.
    SparseCholesky(std::int64_t n, const std::int64_t* indptr, const std::int64_t* indices,
                   const double* values, double pivot_tolerance);

    /// Solves A X = B for a column-major (n, k) right-hand side B; returns X (n, k).
    /// Columns are solved in parallel over num_threads() threads; each column is
    /// solved on its own, so X does not depend on the thread count.
    Eigen::MatrixXd solve(const Eigen::Ref<const Eigen::MatrixXd>& rhs) const;

    std::int64_t size() const { return n_; }
    /// Nonzeros of the factor L (strictly lower part), a measure of fill-in.
    std::int64_t factor_nonzeros() const;
    /// The smallest and largest pivot of D.
    double min_pivot() const { return min_pivot_; }
    double max_pivot() const { return max_pivot_; }

private:
    using Matrix = Eigen::SparseMatrix<double, Eigen::ColMajor, int>;
    std::int64_t n_;
    Eigen::SimplicialLDLT<Matrix, Eigen::Lower, Eigen::AMDOrdering<int>> ldlt_;
    double min_pivot_ = 0.0;
    double max_pivot_ = 0.0;
};

/// Factorises a sequence of symmetric positive-definite matrices that share one
/// sparsity pattern (the systems of an iterative fit): the approximate-minimum-degree
/// ordering and the symbolic analysis are computed once, at construction, and each
/// factorize() computes only the numeric factor.
///
/// Not safe to factorize() while another thread solves.
class PatternCholesky {
public:
    /// Analyses the pattern of the LOWER triangle given in compressed-sparse-column
    /// form (same preconditions as SparseCholesky, without values).
    PatternCholesky(std::int64_t n, const std::int64_t* indptr, const std::int64_t* indices);

    /// Factorises the matrix with this pattern and the given values (one per stored
    /// entry, in CSC order). Throws std::invalid_argument as SparseCholesky does when
    /// the matrix is singular or indefinite; the object then holds no factor.
    void factorize(const double* values, double pivot_tolerance);

    /// Solves A X = B with the last factor (in parallel over columns, like
    /// SparseCholesky::solve). Throws std::logic_error when there is no factor.
    Eigen::MatrixXd solve(const Eigen::Ref<const Eigen::MatrixXd>& rhs) const;

    std::int64_t size() const { return n_; }
    std::int64_t stored_entries() const { return lower_.nonZeros(); }
    bool factorised() const { return factorised_; }
    double min_pivot() const { return min_pivot_; }
    double max_pivot() const { return max_pivot_; }

private:
    using Matrix = Eigen::SparseMatrix<double, Eigen::ColMajor, int>;
    std::int64_t n_;
    Matrix lower_;
    Eigen::SimplicialLDLT<Matrix, Eigen::Lower, Eigen::AMDOrdering<int>> ldlt_;
    bool factorised_ = false;
    double min_pivot_ = 0.0;
    double max_pivot_ = 0.0;
};

}  // namespace tpscore

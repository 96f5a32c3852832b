// Sparse direct solve of symmetric positive-definite systems: factorise once, solve
// for many right-hand sides.
#pragma once

#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <cstdint>
#include <vector>

#include "tpscore/types.hpp"

namespace tpscore {

struct SupernodeKernels;

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
/// sparsity pattern (the systems of an iterative fit) as P A P^T = L L^T, with a
/// supernodal multifrontal Cholesky factorisation.
///
/// Everything that depends on the pattern alone is computed once, at construction:
/// the fill-reducing ordering P (the caller's, or approximate minimum degree), the
/// elimination tree, the supernodes (runs of consecutive columns of L that share one
/// row structure; small runs are merged with their parent when that adds few
/// explicit zeros) and, for every stored entry and every child's update matrix,
/// where it lands in its supernode's dense front. Each factorize() then only
/// assembles the fronts and factorises them with dense kernels
/// (tpscore/supernode_kernels.hpp), so nearly all the arithmetic runs in blocked
/// matrix-product kernels instead of scalar sparse loops.
///
/// Disjoint subtrees of the supernode tree are factorised on separate threads (split
/// for num_threads() at construction), when the factorisation is large enough to gain
/// from it (40 million multiply-adds). Every supernode sums its inputs in one fixed
/// order whatever the thread it runs on, so the factor, and every solution, does not
/// depend on the thread count.
///
/// Not safe to factorize() while another thread solves.
class PatternCholesky {
public:
    /// Analyses the pattern of the LOWER triangle given in compressed-sparse-column
    /// form (same preconditions as SparseCholesky, without values). `ordering` is
    /// null (approximate minimum degree) or n entries, a permutation of 0 .. n-1:
    /// ordering[k] is the unknown eliminated k-th (row and column k of P A P^T).
    /// The factorisation may reorder it further, only among unknowns whose order
    /// does not change the factor's pattern (a postorder of its elimination tree).
    PatternCholesky(std::int64_t n, const std::int64_t* indptr, const std::int64_t* indices,
                    const std::int64_t* ordering);

    /// Factorises the matrix with this pattern and the given values (one per stored
    /// entry, in CSC order). Throws std::invalid_argument as SparseCholesky does when
    /// the matrix is singular or indefinite (a pivot of D in the equivalent
    /// P A P^T = L' D L'^T, i.e. a squared diagonal entry of L, that is not clearly
    /// positive); the object then holds no factor. The message names the first
    /// failing pivot in elimination order, whatever the thread count. `workers`: the
    /// threads that may share the independent subtrees, as for the other kernels
    /// (parallel_rows: <= 0 for tpscore::num_threads(), 1 for this thread alone); the
    /// factor is the same, bit for bit, with any count.
    void factorize(const double* values, double pivot_tolerance, int workers = 0);

    /// Solves A X = B with the last factor, column by column and in parallel over
    /// columns (each column on its own, so X does not depend on the thread count).
    /// Throws std::logic_error when there is no factor.
    Eigen::MatrixXd solve(const Eigen::Ref<const Eigen::MatrixXd>& rhs) const;

    std::int64_t size() const { return n_; }
    std::int64_t stored_entries() const { return static_cast<std::int64_t>(entry_source_.size()); }
    bool factorised() const { return factorised_; }
    double min_pivot() const { return min_pivot_; }
    double max_pivot() const { return max_pivot_; }
    /// Entries of L stored below the diagonal (explicit zeros of merged supernodes
    /// included).
    std::int64_t factor_nonzeros() const { return factor_nonzeros_; }
    /// Number of supernodes.
    std::int64_t supernodes() const { return static_cast<std::int64_t>(first_column_.size()) - 1; }
    /// Groups of disjoint subtrees that threads factorise concurrently (0: the whole
    /// factorisation runs on the calling thread).
    std::int64_t thread_groups() const { return static_cast<std::int64_t>(groups_.size()); }
    /// Multiply-adds of one factorize(): a measure of its cost.
    double factor_multiply_adds() const { return total_work_; }
    /// The order of elimination actually used: entry k is the unknown eliminated k-th.
    const std::vector<std::int64_t>& ordering() const { return order_; }

private:
    // Factorises supernode s from its entries and its children's updates; returns -1
    // or the column (in elimination order) of its first non-positive pivot.
    std::int64_t factor_supernode(std::int64_t s, const double* values,
                                  const SupernodeKernels& kernels);

    std::int64_t n_;
    std::vector<std::int64_t> order_;           // elimination order: order_[k] = unknown
    // Supernode s owns the columns first_column_[s] .. first_column_[s + 1] - 1 (in
    // elimination order) and the rows row_index_[row_start_[s] .. row_start_[s + 1]),
    // its own columns first; its panel starts at panel_start_[s] in factor_ and its
    // update matrix at update_start_[s] in update_.
    std::vector<std::int64_t> first_column_;
    std::vector<std::int64_t> row_start_;
    std::vector<std::int32_t> row_index_;
    std::vector<std::int64_t> panel_start_;
    std::vector<std::int64_t> update_start_;
    std::vector<std::int64_t> parent_;          // parent supernode, -1 at a root
    std::vector<std::int64_t> child_start_;     // children of s: child_[child_start_[s] ..)
    std::vector<std::int64_t> child_;
    // Child c's update rows land at rows relative_[relative_start_[c] ..) of its
    // parent's front.
    std::vector<std::int64_t> relative_start_;
    std::vector<std::int32_t> relative_;
    // ... in runs of consecutive rows: run_bound_[run_start_[c] ..] are the indices
    // (into c's update rows) where runs begin, then the number of rows.
    std::vector<std::int64_t> run_start_;
    std::vector<std::int32_t> run_bound_;
    // The stored entries of supernode s: entry_source_[k] (index into the caller's
    // values) goes to panel offset entry_target_[k], for k in entry_start_[s] ..
    std::vector<std::int64_t> entry_start_;
    std::vector<std::int32_t> entry_source_;
    std::vector<std::int32_t> entry_target_;
    std::vector<double> work_;                  // multiply-adds of each supernode
    std::vector<double> subtree_work_;          // ... and of its subtree
    std::vector<std::int64_t> subtree_first_;   // the subtree of s is subtree_first_[s] .. s
    // Subtrees factorised in parallel: groups_[g] lists the roots of group g's
    // subtrees; group_of_[s] is s's group, or -1 for the supernodes factorised after
    // the groups, on one thread. Fixed at construction (from the thread count then),
    // because the update matrices' memory is laid out for it.
    std::vector<std::vector<std::int64_t>> groups_;
    std::vector<std::int64_t> group_of_;
    double total_work_ = 0.0;
    std::int64_t factor_nonzeros_ = 0;

    std::vector<double> factor_;
    std::vector<double> update_;
    std::vector<double> pivots_;                // in elimination order
    bool factorised_ = false;
    double min_pivot_ = 0.0;
    double max_pivot_ = 0.0;
};

/// PatternCholesky's predecessor and reference: Eigen's SimplicialLDLT with an
/// approximate-minimum-degree ordering, the ordering and symbolic analysis done
/// once, each factorize() a column-by-column (scalar) numeric factorisation.
/// Same contract as PatternCholesky.
class SimplicialPatternCholesky {
public:
    SimplicialPatternCholesky(std::int64_t n, const std::int64_t* indptr,
                              const std::int64_t* indices);
    void factorize(const double* values, double pivot_tolerance);
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

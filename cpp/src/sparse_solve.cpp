// Sparse direct solve (see tpscore/sparse_solve.hpp).
#include "tpscore/sparse_solve.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <cstdint>
#include <numeric>
#include <sstream>
#include <stdexcept>
#include <tuple>
#include <utility>
#include <vector>

#include "tpscore/kdtree.hpp"  // parallel_rows
#include "tpscore/parallel.hpp"
#include "tpscore/supernode_kernels.hpp"

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

[[noreturn]] void throw_zero_pivot() {
    throw std::invalid_argument(
        "matrix is singular: its LDL^T factorisation met an exactly zero pivot");
}

[[noreturn]] void throw_not_positive_definite(double min_pivot, double scale) {
    std::ostringstream message;
    message.precision(3);
    message << "matrix is not positive definite: the smallest pivot of its LDL^T "
               "factorisation is "
            << min_pivot << " against a largest |pivot| of " << scale
            << " (it is singular or indefinite)";
    throw std::invalid_argument(message.str());
}

// Throws unless the factorisation succeeded with every pivot of D clearly positive;
// returns the (smallest, largest) pivot.
std::pair<double, double> checked_pivots(const Ldlt& ldlt, std::int64_t n,
                                         double pivot_tolerance) {
    if (ldlt.info() != Eigen::Success) throw_zero_pivot();
    if (n == 0) return {0.0, 0.0};
    const Eigen::VectorXd& pivots = ldlt.vectorD();
    const double min_pivot = pivots.minCoeff();
    const double max_pivot = pivots.maxCoeff();
    const double scale = pivots.cwiseAbs().maxCoeff();
    if (!(min_pivot > pivot_tolerance * scale)) throw_not_positive_definite(min_pivot, scale);
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

SimplicialPatternCholesky::SimplicialPatternCholesky(std::int64_t n, const std::int64_t* indptr,
                                                     const std::int64_t* indices)
    : n_(n), lower_(lower_from_csc(n, indptr, indices, nullptr)) {
    ldlt_.analyzePattern(lower_);
}

void SimplicialPatternCholesky::factorize(const double* values, double pivot_tolerance) {
    factorised_ = false;
    std::copy(values, values + lower_.nonZeros(), lower_.valuePtr());
    ldlt_.factorize(lower_);
    std::tie(min_pivot_, max_pivot_) = checked_pivots(ldlt_, n_, pivot_tolerance);
    factorised_ = true;
}

Eigen::MatrixXd SimplicialPatternCholesky::solve(const Eigen::Ref<const Eigen::MatrixXd>& rhs) const {
    if (!factorised_) throw std::logic_error("no factor: factorize() has not succeeded");
    return solve_columns(ldlt_, n_, rhs);
}


// --- PatternCholesky: supernodal multifrontal LL^T ----------------------------------
//
// Symbolic analysis (once per pattern), in the terms of Liu's and Davis's books:
//   1. an elimination order (the caller's or AMD), postordered along the elimination
//      tree so that every subtree is a contiguous run of columns;
//   2. the column counts of L from the row subtrees;
//   3. supernodes: a column joins its child's supernode when the child's structure
//      is the column plus the column's own structure; then small supernodes are
//      merged into their parents when few explicit zeros result (relaxed
//      amalgamation), because dense kernels on tiny blocks run far below their
//      peak speed;
//   4. each supernode's row structure, where its stored entries land in its panel,
//      and where each child's update rows land in its front.
// Numeric factorisation (each factorize()): supernodes in postorder, each one
// assembling its front (its entries, plus its children's update matrices added at
// their relative rows) and factorising it with the dense kernels.

namespace {

using Index = std::int64_t;

// The lower triangle of P A P^T by columns: column j holds rows row[start[j] ..
// start[j + 1]) (all >= j, increasing), the k-th of them the caller's stored entry
// source[k].
struct PermutedLower {
    std::vector<Index> start;
    std::vector<std::int32_t> row;
    std::vector<Index> source;
};

PermutedLower permute_lower(Index n, const Index* indptr, const Index* indices,
                            const std::vector<Index>& position) {
    const Index nnz = indptr[n];
    // Bucket the entries by their new row first; taking them row by row into their
    // new columns then leaves every column's rows in increasing order.
    std::vector<Index> row_end(static_cast<std::size_t>(n + 1), 0);
    PermutedLower out;
    out.start.assign(static_cast<std::size_t>(n + 1), 0);
    for (Index j = 0; j < n; ++j)
        for (Index k = indptr[j]; k < indptr[j + 1]; ++k) {
            const Index a = position[indices[k]], b = position[j];
            ++row_end[std::max(a, b) + 1];
            ++out.start[std::min(a, b) + 1];
        }
    std::partial_sum(row_end.begin(), row_end.end(), row_end.begin());
    std::partial_sum(out.start.begin(), out.start.end(), out.start.begin());
    struct Entry {
        Index column, source;
    };
    std::vector<Entry> by_row(static_cast<std::size_t>(nnz));
    for (Index j = 0; j < n; ++j)
        for (Index k = indptr[j]; k < indptr[j + 1]; ++k) {
            const Index a = position[indices[k]], b = position[j];
            by_row[row_end[std::max(a, b)]++] = Entry{std::min(a, b), k};
        }
    // row_end[i] now ends row i's bucket
    out.row.resize(static_cast<std::size_t>(nnz));
    out.source.resize(static_cast<std::size_t>(nnz));
    std::vector<Index> next(out.start.begin(), out.start.end() - 1);
    for (Index i = 0, k = 0; i < n; ++i)
        for (; k < row_end[i]; ++k) {
            const Index slot = next[by_row[k].column]++;
            out.row[slot] = static_cast<std::int32_t>(i);
            out.source[slot] = by_row[k].source;
        }
    return out;
}

// The same pattern by rows, without the diagonal: row i holds the columns
// column[start[i] .. start[i + 1]), all < i.
struct RowPattern {
    std::vector<Index> start;
    std::vector<std::int32_t> column;
};

RowPattern rows_of(Index n, const PermutedLower& lower) {
    RowPattern out;
    out.start.assign(static_cast<std::size_t>(n + 1), 0);
    for (Index j = 0; j < n; ++j)
        for (Index k = lower.start[j]; k < lower.start[j + 1]; ++k)
            if (lower.row[k] > j) ++out.start[lower.row[k] + 1];
    std::partial_sum(out.start.begin(), out.start.end(), out.start.begin());
    out.column.resize(static_cast<std::size_t>(out.start[n]));
    std::vector<Index> next(out.start.begin(), out.start.end() - 1);
    for (Index j = 0; j < n; ++j)
        for (Index k = lower.start[j]; k < lower.start[j + 1]; ++k)
            if (lower.row[k] > j) out.column[next[lower.row[k]]++] = static_cast<std::int32_t>(j);
    return out;
}

// Elimination tree (Liu's algorithm with path compression); -1 marks a root.
std::vector<Index> elimination_tree(Index n, const RowPattern& rows) {
    std::vector<Index> parent(static_cast<std::size_t>(n), -1);
    std::vector<Index> ancestor(static_cast<std::size_t>(n), -1);
    for (Index k = 0; k < n; ++k)
        for (Index p = rows.start[k]; p < rows.start[k + 1]; ++p) {
            Index i = rows.column[p];
            while (i != -1 && i < k) {
                const Index next = ancestor[i];
                ancestor[i] = k;
                if (next == -1) parent[i] = k;
                i = next;
            }
        }
    return parent;
}

// A postorder of a forest: post[k] is the k-th node; children in increasing order.
std::vector<Index> postorder(const std::vector<Index>& parent) {
    const Index n = static_cast<Index>(parent.size());
    std::vector<Index> head(static_cast<std::size_t>(n), -1), next(static_cast<std::size_t>(n), -1);
    for (Index j = n - 1; j >= 0; --j)
        if (parent[j] != -1) {
            next[j] = head[parent[j]];
            head[parent[j]] = j;
        }
    std::vector<Index> post;
    post.reserve(static_cast<std::size_t>(n));
    std::vector<Index> stack;
    for (Index root = 0; root < n; ++root) {
        if (parent[root] != -1) continue;
        stack.push_back(root);
        while (!stack.empty()) {
            const Index p = stack.back();
            const Index child = head[p];
            if (child == -1) {
                stack.pop_back();
                post.push_back(p);
            } else {
                head[p] = next[child];
                stack.push_back(child);
            }
        }
    }
    return post;
}

// Entries of each column of L, diagonal included: row i of L is the union of the
// tree paths from the columns of row i of A up to i (its row subtree).
std::vector<Index> column_counts(Index n, const RowPattern& rows, const std::vector<Index>& parent) {
    std::vector<Index> count(static_cast<std::size_t>(n), 1);
    std::vector<Index> mark(static_cast<std::size_t>(n), -1);
    for (Index i = 0; i < n; ++i) {
        mark[i] = i;
        for (Index p = rows.start[i]; p < rows.start[i + 1]; ++p)
            for (Index j = rows.column[p]; mark[j] != i; j = parent[j]) {
                ++count[j];
                mark[j] = i;
            }
    }
    return count;
}

// Whether a supernode of `columns` columns and `entries` stored entries, `zeros` of
// them explicit zeros, may be formed by merging (CHOLMOD's default relaxation: any
// merge up to 4 columns, then a shrinking share of zeros as the supernode grows).
bool merge_is_worth_it(Index columns, double entries, double zeros) {
    const double share = zeros / entries;
    if (columns <= 4) return true;
    if (columns <= 16) return share < 0.8;
    if (columns <= 48) return share < 0.1;
    return share < 0.05;
}

// Multiply-adds of one supernode's partial factorisation and assembly.
double front_work(Index rows, Index columns) {
    const double c = static_cast<double>(columns);
    const double b = static_cast<double>(rows - columns);
    return c * c * c / 6.0 + b * c * c / 2.0 + b * b * c / 2.0 + static_cast<double>(rows) * c +
           b * b;
}

// Splits the supernode tree into disjoint subtrees, in `threads` groups of about
// equal work: starting from the roots, keep opening the heaviest subtree (its root
// then runs after the groups, on one thread) until the groups, filled heaviest
// first into the lightest, balance within 10 %. Each group lists its subtree roots
// in increasing order.
std::vector<std::vector<Index>> schedule_subtrees(Index threads, const std::vector<Index>& parent,
                                                  const std::vector<Index>& child_start,
                                                  const std::vector<Index>& child,
                                                  const std::vector<double>& subtree_work) {
    std::vector<Index> subtrees;
    for (Index s = 0; s < static_cast<Index>(parent.size()); ++s)
        if (parent[s] == -1) subtrees.push_back(s);
    std::vector<std::vector<Index>> groups;
    for (int attempt = 0; attempt < 64; ++attempt) {
        std::sort(subtrees.begin(), subtrees.end(),
                  [&](Index a, Index b) { return subtree_work[a] > subtree_work[b]; });
        groups.assign(static_cast<std::size_t>(threads), {});
        std::vector<double> load(static_cast<std::size_t>(threads), 0.0);
        for (Index root : subtrees) {
            const auto lightest = std::min_element(load.begin(), load.end()) - load.begin();
            groups[lightest].push_back(root);
            load[lightest] += subtree_work[root];
        }
        const double heaviest = *std::max_element(load.begin(), load.end());
        const double mean = std::accumulate(load.begin(), load.end(), 0.0) / static_cast<double>(threads);
        const Index widest = subtrees.front();
        if (heaviest <= 1.1 * mean || child_start[widest] == child_start[widest + 1]) break;
        subtrees.erase(subtrees.begin());
        for (Index c = child_start[widest]; c < child_start[widest + 1]; ++c) subtrees.push_back(child[c]);
    }
    for (auto& group : groups) std::sort(group.begin(), group.end());
    groups.erase(std::remove_if(groups.begin(), groups.end(), [](const auto& g) { return g.empty(); }),
                 groups.end());
    return groups;
}

// Places the update matrices of the supernodes in `sequence` (factorised in that
// order, children before parents) in one arena starting at `base`: each goes to the
// lowest offset where it overlaps no update matrix still waiting for its parent, its
// own children's included (they are read while it is assembled). Reusing the memory
// of consumed updates keeps the working set, and so the extend-add traffic, in cache:
// without reuse the updates of a 4,000-unknown lattice system take 36 MB. Sets
// start[s]; returns the arena's size.
Index place_updates(const std::vector<Index>& sequence, const std::vector<Index>& size,
                    const std::vector<Index>& parent, Index base, std::vector<Index>& start) {
    struct Interval {
        Index begin, end, owner;
    };
    std::vector<Interval> live;  // sorted by begin
    Index extent = 0;
    for (Index s : sequence) {
        Index offset = 0;
        auto at = live.begin();
        for (; at != live.end(); ++at) {
            if (offset + size[s] <= at->begin) break;
            offset = std::max(offset, at->end);
        }
        live.insert(at, Interval{offset, offset + size[s], s});
        start[s] = base + offset;
        extent = std::max(extent, offset + size[s]);
        live.erase(std::remove_if(live.begin(), live.end(),
                                  [&](const Interval& i) { return parent[i.owner] == s; }),
                   live.end());
    }
    return extent;
}

constexpr Index kSucceeded = -1;
constexpr Index kNotRun = -2;
constexpr Index kSkipped = -3;  // a descendant failed

// Below this many multiply-adds (about 2 ms of work) a factorisation runs on the
// calling thread: a thread pool's hand-over costs microseconds, but on a busy machine
// a helper can wait milliseconds for a core. Measured on 2 cores: the registration's
// default system (1,440 unknowns, 30 million multiply-adds) factorises in 2.1 ms on two
// threads against 3.4 ms on one, and a transfer's modelling stage (ten of them, the
// other core otherwise idle) takes 5-10 ms less. At 10 million the closing eyes' local
// corrections (14-24 million each, both sides of the cut at once) went parallel too and
// made that transfer slower.
constexpr double kParallelWork = 2.5e7;

}  // namespace

PatternCholesky::PatternCholesky(std::int64_t n, const std::int64_t* indptr,
                                 const std::int64_t* indices, const std::int64_t* ordering)
    : n_(n) {
    // 1. Elimination order, postordered.
    std::vector<Index> order(static_cast<std::size_t>(n));
    if (ordering != nullptr) {
        std::copy(ordering, ordering + n, order.begin());
    } else if (n > 0) {
        const Matrix lower = lower_from_csc(n, indptr, indices, nullptr);
        Eigen::PermutationMatrix<Eigen::Dynamic, Eigen::Dynamic, int> permutation;
        Eigen::AMDOrdering<int>()(lower.selfadjointView<Eigen::Lower>(), permutation);
        for (Index k = 0; k < n; ++k) order[k] = permutation.indices()[k];
    }
    std::vector<Index> position(static_cast<std::size_t>(n));
    for (Index k = 0; k < n; ++k) position[order[k]] = k;
    std::vector<Index> parent;
    {
        const PermutedLower lower = permute_lower(n, indptr, indices, position);
        const std::vector<Index> tree = elimination_tree(n, rows_of(n, lower));
        const std::vector<Index> post = postorder(tree);
        std::vector<Index> renumbered(static_cast<std::size_t>(n));
        for (Index k = 0; k < n; ++k) renumbered[post[k]] = k;
        parent.resize(static_cast<std::size_t>(n));
        order_.resize(static_cast<std::size_t>(n));
        for (Index k = 0; k < n; ++k) {
            order_[k] = order[post[k]];
            parent[k] = tree[post[k]] == -1 ? -1 : renumbered[tree[post[k]]];
        }
    }
    for (Index k = 0; k < n; ++k) position[order_[k]] = k;
    const PermutedLower lower = permute_lower(n, indptr, indices, position);

    // 2. Column counts.
    const std::vector<Index> count = column_counts(n, rows_of(n, lower), parent);

    // 3. Fundamental supernodes, then relaxed amalgamation from the roots down (a
    // parent has a higher number than its children, so when a child is considered,
    // its parent has already absorbed what it will above).
    std::vector<Index> first;        // first column of each supernode
    for (Index j = 0; j < n; ++j)
        if (j == 0 || parent[j - 1] != j || count[j - 1] != count[j] + 1) first.push_back(j);
    const Index fundamental = static_cast<Index>(first.size());
    first.push_back(n);
    std::vector<Index> supernode_of(static_cast<std::size_t>(n));
    for (Index s = 0; s < fundamental; ++s)
        for (Index j = first[s]; j < first[s + 1]; ++j) supernode_of[j] = s;
    std::vector<Index> columns(static_cast<std::size_t>(fundamental)), rows(columns.size()),
        merged_into(columns.size(), -1);
    std::vector<double> zeros(columns.size(), 0.0);
    for (Index s = 0; s < fundamental; ++s) {
        columns[s] = first[s + 1] - first[s];
        rows[s] = count[first[s]];
    }
    auto representative = [&](Index s) {
        while (merged_into[s] != -1) s = merged_into[s];
        return s;
    };
    for (Index s = fundamental - 1; s >= 0; --s) {
        const Index last = first[s] + columns[s] - 1;
        if (parent[last] == -1) continue;
        const Index q = representative(supernode_of[parent[last]]);
        if (first[q] != last + 1) continue;  // not adjacent: merging would need a reorder
        const Index merged_columns = columns[s] + columns[q];
        const Index merged_rows = columns[s] + rows[q];
        const double merged_zeros = zeros[s] + zeros[q] +
                                    static_cast<double>(columns[s]) * static_cast<double>(merged_rows - rows[s]);
        const double entries = static_cast<double>(merged_columns) * static_cast<double>(merged_rows) -
                               0.5 * static_cast<double>(merged_columns) * static_cast<double>(merged_columns - 1);
        if (!merge_is_worth_it(merged_columns, entries, merged_zeros)) continue;
        merged_into[s] = q;
        first[q] = first[s];
        columns[q] = merged_columns;
        rows[q] = merged_rows;
        zeros[q] = merged_zeros;
    }
    first_column_.clear();
    for (Index s = 0; s < fundamental; ++s)
        if (merged_into[s] == -1) first_column_.push_back(first[s]);
    const Index supernodes = static_cast<Index>(first_column_.size());
    first_column_.push_back(n);
    for (Index s = 0; s < supernodes; ++s)
        for (Index j = first_column_[s]; j < first_column_[s + 1]; ++j) supernode_of[j] = s;
    parent_.assign(static_cast<std::size_t>(supernodes), -1);
    for (Index s = 0; s < supernodes; ++s) {
        const Index up = parent[first_column_[s + 1] - 1];
        parent_[s] = up == -1 ? -1 : supernode_of[up];
    }
    child_start_.assign(static_cast<std::size_t>(supernodes + 1), 0);
    for (Index s = 0; s < supernodes; ++s)
        if (parent_[s] != -1) ++child_start_[parent_[s] + 1];
    std::partial_sum(child_start_.begin(), child_start_.end(), child_start_.begin());
    child_.resize(static_cast<std::size_t>(child_start_[supernodes]));
    {
        std::vector<Index> next(child_start_.begin(), child_start_.end() - 1);
        for (Index s = 0; s < supernodes; ++s)
            if (parent_[s] != -1) child_[next[parent_[s]]++] = s;
    }

    // 4. Row structures (the supernode's columns, then the union of its columns'
    // entries and its children's update rows, sorted), panel and update offsets,
    // the relative rows of each child's update, and each entry's panel offset.
    row_start_.assign(1, 0);
    row_index_.clear();
    panel_start_.assign(1, 0);
    relative_start_.assign(static_cast<std::size_t>(supernodes), 0);
    entry_start_.assign(1, 0);
    entry_source_.clear();
    entry_target_.clear();
    work_.assign(static_cast<std::size_t>(supernodes), 0.0);
    std::vector<Index> mark(static_cast<std::size_t>(n), -1);
    std::vector<Index> place(static_cast<std::size_t>(n), 0);
    for (Index s = 0; s < supernodes; ++s) {
        const Index begin = first_column_[s], end = first_column_[s + 1];
        const std::size_t structure = row_index_.size();
        for (Index j = begin; j < end; ++j) {
            mark[j] = s;
            row_index_.push_back(static_cast<std::int32_t>(j));
        }
        for (Index j = begin; j < end; ++j)
            for (Index k = lower.start[j]; k < lower.start[j + 1]; ++k)
                if (mark[lower.row[k]] != s) {
                    mark[lower.row[k]] = s;
                    row_index_.push_back(lower.row[k]);
                }
        for (Index c = child_start_[s]; c < child_start_[s + 1]; ++c) {
            const Index child = child_[c];
            const Index child_columns = first_column_[child + 1] - first_column_[child];
            for (Index r = row_start_[child] + child_columns; r < row_start_[child + 1]; ++r)
                if (mark[row_index_[r]] != s) {
                    mark[row_index_[r]] = s;
                    row_index_.push_back(row_index_[r]);
                }
        }
        std::sort(row_index_.begin() + static_cast<std::ptrdiff_t>(structure) + (end - begin),
                  row_index_.end());
        row_start_.push_back(static_cast<Index>(row_index_.size()));
        const Index height = row_start_[s + 1] - row_start_[s];
        const Index width = end - begin;
        for (Index r = 0; r < height; ++r) place[row_index_[row_start_[s] + r]] = r;
        for (Index c = child_start_[s]; c < child_start_[s + 1]; ++c) {
            const Index child = child_[c];
            const Index child_columns = first_column_[child + 1] - first_column_[child];
            relative_start_[child] = static_cast<Index>(relative_.size());
            for (Index r = row_start_[child] + child_columns; r < row_start_[child + 1]; ++r)
                relative_.push_back(static_cast<std::int32_t>(place[row_index_[r]]));
        }
        if (height * width > std::numeric_limits<std::int32_t>::max())
            throw std::length_error("sparse factor: a supernode holds more than 2^31 entries");
        // Rows are increasing within each column, and so are their places: the
        // entries come in panel order and are written front to back.
        for (Index j = begin; j < end; ++j)
            for (Index k = lower.start[j]; k < lower.start[j + 1]; ++k) {
                entry_target_.push_back(static_cast<std::int32_t>((j - begin) * height + place[lower.row[k]]));
                entry_source_.push_back(static_cast<std::int32_t>(lower.source[k]));
            }
        entry_start_.push_back(static_cast<Index>(entry_source_.size()));
        panel_start_.push_back(panel_start_[s] + height * width);
        factor_nonzeros_ += height * width - width * (width + 1) / 2;
        work_[s] = front_work(height, width);
    }
    // The runs of each child's update rows that land on consecutive front rows.
    run_start_.assign(static_cast<std::size_t>(supernodes), 0);
    run_bound_.clear();
    for (Index s = 0; s < supernodes; ++s) {
        if (parent_[s] == -1) continue;
        const Index size = row_start_[s + 1] - row_start_[s] - (first_column_[s + 1] - first_column_[s]);
        const std::int32_t* relative = relative_.data() + relative_start_[s];
        run_start_[s] = static_cast<Index>(run_bound_.size());
        run_bound_.push_back(0);
        for (Index a = 1; a < size; ++a)
            if (relative[a] != relative[a - 1] + 1) run_bound_.push_back(static_cast<std::int32_t>(a));
        run_bound_.push_back(static_cast<std::int32_t>(size));
    }
    subtree_work_.assign(work_.begin(), work_.end());
    subtree_first_.resize(static_cast<std::size_t>(supernodes));
    for (Index s = 0; s < supernodes; ++s) subtree_first_[s] = s;
    for (Index s = 0; s < supernodes; ++s)
        if (parent_[s] != -1) {
            subtree_work_[parent_[s]] += subtree_work_[s];
            subtree_first_[parent_[s]] = std::min(subtree_first_[parent_[s]], subtree_first_[s]);
        }
    total_work_ = std::accumulate(work_.begin(), work_.end(), 0.0);

    // 5. Which thread group factorises which subtrees, and where each update matrix
    // lives (see schedule_subtrees and place_updates).
    groups_.clear();
    if (num_threads() > 1 && total_work_ >= kParallelWork)
        groups_ = schedule_subtrees(num_threads(), parent_, child_start_, child_, subtree_work_);
    group_of_.assign(static_cast<std::size_t>(supernodes), -1);
    for (std::size_t g = 0; g < groups_.size(); ++g)
        for (Index root : groups_[g])
            for (Index s = subtree_first_[root]; s <= root; ++s) group_of_[s] = static_cast<Index>(g);
    std::vector<Index> update_size(static_cast<std::size_t>(supernodes));
    for (Index s = 0; s < supernodes; ++s) {
        const Index remaining = row_start_[s + 1] - row_start_[s] - (first_column_[s + 1] - first_column_[s]);
        update_size[s] = remaining * remaining;
    }
    update_start_.assign(static_cast<std::size_t>(supernodes), 0);
    Index arena = 0;
    for (Index g = -1; g < static_cast<Index>(groups_.size()); ++g) {
        std::vector<Index> sequence;
        for (Index s = 0; s < supernodes; ++s)
            if (group_of_[s] == g) sequence.push_back(s);
        arena += place_updates(sequence, update_size, parent_, arena, update_start_);
    }
    factor_.assign(static_cast<std::size_t>(panel_start_.back()), 0.0);
    update_.assign(static_cast<std::size_t>(arena), 0.0);
    pivots_.assign(static_cast<std::size_t>(n), 0.0);
}

std::int64_t PatternCholesky::factor_supernode(std::int64_t s, const double* values,
                                               const SupernodeKernels& kernels) {
    const Index begin = first_column_[s];
    const Index width = first_column_[s + 1] - begin;
    const Index height = row_start_[s + 1] - row_start_[s];
    const Index remaining = height - width;
    double* panel = factor_.data() + panel_start_[s];
    double* update = update_.data() + update_start_[s];
    // Only the lower triangles of the diagonal block and of the update matrix are
    // read or written.
    for (Index j = 0; j < width; ++j) std::fill(panel + j * height + j, panel + (j + 1) * height, 0.0);
    for (Index b = 0; b < remaining; ++b)
        std::fill(update + b * remaining + b, update + (b + 1) * remaining, 0.0);
    for (Index k = entry_start_[s]; k < entry_start_[s + 1]; ++k)
        panel[entry_target_[k]] = values[entry_source_[k]];
    // Extend-add: each child's update matrix (lower triangle) goes to the rows and
    // columns of this front that its rows map to. Those of the front's own columns
    // are in the panel, the others in the update matrix. Rows that map to
    // consecutive rows come in runs, added as contiguous (vectorised) slices.
    for (Index c = child_start_[s]; c < child_start_[s + 1]; ++c) {
        const Index child = child_[c];
        const Index size = row_start_[child + 1] - row_start_[child] -
                           (first_column_[child + 1] - first_column_[child]);
        const std::int32_t* relative = relative_.data() + relative_start_[child];
        const std::int32_t* bound = run_bound_.data() + run_start_[child];
        const double* source = update_.data() + update_start_[child];
        Index run = 0;
        for (Index b = 0; b < size; ++b) {
            while (bound[run + 1] <= b) ++run;
            const Index column = relative[b];
            const double* from = source + b * size;
            double* to = column < width ? panel + column * height
                                        : update + (column - width) * remaining - width;
            for (Index a = b, r = run; a < size; a = bound[++r]) {
                double* __restrict target = to + relative[a];
                const double* __restrict added = from + a;
                const Index length = bound[r + 1] - a;
                for (Index i = 0; i < length; ++i) target[i] += added[i];
            }
        }
    }
    const std::ptrdiff_t failed =
        kernels.factor_front(panel, height, width, update, pivots_.data() + begin);
    return failed < 0 ? kSucceeded : begin + failed;
}

void PatternCholesky::factorize(const double* values, double pivot_tolerance, int workers) {
    factorised_ = false;
    if (n_ == 0) {
        min_pivot_ = max_pivot_ = 0.0;
        factorised_ = true;
        return;
    }
    const SupernodeKernels& kernels = supernode_kernels();
    const Index supernodes = static_cast<Index>(parent_.size());
    std::vector<Index> outcome(static_cast<std::size_t>(supernodes), kNotRun);
    auto run = [&](Index s) {
        for (Index c = child_start_[s]; c < child_start_[s + 1]; ++c)
            if (outcome[child_[c]] != kSucceeded) {
                outcome[s] = kSkipped;
                return;
            }
        outcome[s] = factor_supernode(s, values, kernels);
    };

    if (groups_.empty()) {
        for (Index s = 0; s < supernodes; ++s) run(s);
    } else {
        // Each thread claims the next unclaimed group, so a thread that starts late
        // (the machine is busy) leaves its share to the others instead of holding
        // them up; with workers == 1 this thread claims them all.
        std::atomic<std::size_t> next{0};
        parallel_rows(groups_.size(), 1, workers, [&](std::size_t, std::size_t) {
            for (std::size_t g = next++; g < groups_.size(); g = next++)
                for (Index root : groups_[g])
                    for (Index s = subtree_first_[root]; s <= root; ++s) run(s);
        });
        for (Index s = 0; s < supernodes; ++s)
            if (group_of_[s] == -1) run(s);
    }

    // The failure reported is the first in elimination order: every column before it
    // belongs to a supernode without a failed descendant, so it was factorised
    // whatever the schedule.
    for (Index s = 0; s < supernodes; ++s)
        if (outcome[s] >= 0) {
            const Index column = outcome[s];
            const double pivot = pivots_[column];
            if (pivot == 0.0) throw_zero_pivot();
            double scale = std::abs(pivot);
            for (Index j = 0; j < column; ++j) scale = std::max(scale, pivots_[j]);
            throw_not_positive_definite(pivot, scale);
        }
    const auto [smallest, largest] = std::minmax_element(pivots_.begin(), pivots_.end());
    if (!(*smallest > pivot_tolerance * *largest)) throw_not_positive_definite(*smallest, *largest);
    min_pivot_ = *smallest;
    max_pivot_ = *largest;
    factorised_ = true;
}

Eigen::MatrixXd PatternCholesky::solve(const Eigen::Ref<const Eigen::MatrixXd>& rhs) const {
    if (!factorised_) throw std::logic_error("no factor: factorize() has not succeeded");
    Eigen::MatrixXd solution(rhs.rows(), rhs.cols());
    const SupernodeKernels& kernels = supernode_kernels();
    const Index supernodes = static_cast<Index>(parent_.size());
    Index widest_update = 0;
    for (Index s = 0; s < supernodes; ++s)
        widest_update = std::max(widest_update, row_start_[s + 1] - row_start_[s] -
                                                    (first_column_[s + 1] - first_column_[s]));
    // Columns are independent: each is solved alone (so the split over threads
    // cannot change a result); small systems take several columns per chunk.
    const std::size_t min_chunk =
        n_ >= 2000 ? 1 : static_cast<std::size_t>(2000 / std::max<Index>(n_, 1));
    parallel_for(static_cast<std::size_t>(rhs.cols()), min_chunk, [&](std::size_t begin, std::size_t end) {
        std::vector<double> y(static_cast<std::size_t>(n_));
        std::vector<double> below(static_cast<std::size_t>(widest_update));
        for (std::size_t c = begin; c < end; ++c) {
            const Eigen::Index column = static_cast<Eigen::Index>(c);
            for (Index k = 0; k < n_; ++k) y[k] = rhs(order_[k], column);
            for (Index s = 0; s < supernodes; ++s) {
                const Index first = first_column_[s];
                const Index width = first_column_[s + 1] - first;
                const Index height = row_start_[s + 1] - row_start_[s];
                kernels.forward(factor_.data() + panel_start_[s], height, width, y.data() + first,
                                below.data());
                const std::int32_t* rows = row_index_.data() + row_start_[s] + width;
                for (Index r = 0; r < height - width; ++r) y[rows[r]] -= below[r];
            }
            for (Index s = supernodes - 1; s >= 0; --s) {
                const Index first = first_column_[s];
                const Index width = first_column_[s + 1] - first;
                const Index height = row_start_[s + 1] - row_start_[s];
                const std::int32_t* rows = row_index_.data() + row_start_[s] + width;
                for (Index r = 0; r < height - width; ++r) below[r] = y[rows[r]];
                kernels.backward(factor_.data() + panel_start_[s], height, width, y.data() + first,
                                 below.data());
            }
            for (Index k = 0; k < n_; ++k) solution(order_[k], column) = y[k];
        }
    });
    return solution;
}

}  // namespace tpscore

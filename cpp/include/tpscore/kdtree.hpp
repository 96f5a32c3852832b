// A static kd-tree over 3D points: nearest, k-nearest and radius queries.
#pragma once

#include <cstdint>
#include <utility>
#include <vector>

#include "tpscore/types.hpp"

namespace tpscore {

/// The neighbours of a batch of queries in CSR form (see KDTree::query_radius).
struct RadiusNeighbours {
    IndexVector offsets;  ///< (m + 1,)
    IndexVector indices;  ///< neighbour rows of the indexed points
    VectorX distances;    ///< their distances to the query
};

/// Static kd-tree over a copy of (n, 3) points. Immutable after construction, so
/// concurrent queries from several threads are safe.
///
/// Build: each node splits its points at the median of the axis along which their
/// bounding box is widest; nodes of at most `leaf_size` points become leaves. The copy
/// of the points is permuted into leaf order, so a leaf's points are contiguous in
/// memory; indices reported by every query are the ORIGINAL row indices.
///
/// Ties: neighbours are ranked by (squared distance, original index), so among points at
/// exactly the same distance the one with the smaller index comes first. Results are
/// therefore uniquely defined and do not depend on the tree shape or the thread count.
///
/// `workers` (every batched query): the number of threads to use; <= 0 means
/// tpscore::num_threads(); 1 runs serially on the calling thread. It is an upper bound:
/// small batches run serially anyway, and never more than num_threads() are used.
class KDTree {
public:
    /// Builds the tree. Preconditions: points finite; leaf_size >= 1.
    explicit KDTree(const PointsRef& points, int leaf_size = 16);

    /// Number of indexed points.
    std::int64_t size() const;

    /// The k nearest neighbours of each row of `queries` (m, 3), nearest first.
    /// Writes row-major (m, k) `distances` and `indices`; only points at a distance
    /// strictly less than `max_distance` count (pass +inf for no bound); where fewer than
    /// k such points exist, the remaining slots get +inf and index -1.
    /// Preconditions: queries finite; k >= 1; max_distance >= 0 (or +inf).
    /// Threaded over query rows.
    void query(const PointsRef& queries, int k, double max_distance, double* distances,
               std::int64_t* indices, int workers = 0) const;

    /// Appends (index, squared distance) of every point with |p - query| <= `radius`
    /// (3 doubles) to `out`, in no particular (but deterministic) order.
    /// Single-threaded; reentrant. Precondition: radius >= 0.
    void radius_search(const double* query, double radius,
                       std::vector<std::pair<std::int64_t, double>>& out) const;

    /// Number of points with |p - query| <= `radius` (3 doubles): the number of pairs
    /// radius_search appends, counted without collecting them (a box of the tree that
    /// lies inside the ball counts whole, untested). With `whole_below` > 0, a node of
    /// at most that many points that the ball touches counts whole too: an upper bound
    /// on the count, found with fewer node visits and no distance tests.
    /// Single-threaded; reentrant. Precondition: radius >= 0.
    std::int64_t radius_count(const double* query, double radius,
                              std::int64_t whole_below = 0) const;

    /// radius_count of each row of `queries` (m, 3), written to `counts` (m entries):
    /// what query_radius would return per row (or, with `whole_below` > 0, an upper
    /// bound of it), so a caller can judge the size of its output before asking for
    /// it. Threaded over query rows.
    void count_radius(const PointsRef& queries, double radius, std::int64_t* counts,
                      int workers = 0, std::int64_t whole_below = 0) const;

    /// Batched radius query in CSR form: the neighbours of query i (|p - q_i| <= radius)
    /// are indices[offsets[i] .. offsets[i+1]), with their (not squared) distances;
    /// sorted by (distance, index) when `sort` is true, else in a deterministic tree
    /// order. `offsets` has m + 1 entries. Threaded over query rows; output independent
    /// of the thread count.
    RadiusNeighbours query_radius(const PointsRef& queries, double radius, bool sort,
                                  int workers = 0) const;

    /// The indexed points in leaf order: row i is the original point order()[i].
    const Points& permuted_points() const { return points_; }
    /// Original row index of each permuted point.
    const std::vector<std::int64_t>& order() const { return order_; }

    /// A node of the tree: the bounding box of its points, and either two children
    /// (inner node) or a range of permuted points (leaf, left == -1).
    struct Node {
        double lo[3];
        double hi[3];
        std::int64_t begin;
        std::int64_t end;
        std::int32_t left;
        std::int32_t right;
    };

private:
    std::int32_t build(std::int64_t begin, std::int64_t end);

    // Visits the points within `radius` of `query`: whole(node) for a box inside the
    // ball (or, touched by it, of at most `whole_below` points), each(permuted index,
    // squared distance) for a point of a leaf tested alone.
    template <class Whole, class Each>
    void visit_radius(const double* query, double radius, std::int64_t whole_below, Whole&& whole,
                      Each&& each) const;

    template <class Candidates>
    void search_knn(std::int32_t node, const double* q, double bound2, Candidates& best) const;

    Points points_;
    std::vector<std::int64_t> order_;
    std::vector<Node> nodes_;
    int leaf_size_;
};

/// Calls body(begin, end) over [0, n) like tpscore::parallel_for, with at most
/// `workers` threads (<= 0: num_threads(); 1: serial on the calling thread).
/// Shared by the spatial query kernels, whose callers choose the thread count per call.
template <class Body>
void parallel_rows(std::size_t n, std::size_t min_chunk, int workers, Body&& body);

}  // namespace tpscore

#include "tpscore/parallel.hpp"

namespace tpscore {

template <class Body>
void parallel_rows(std::size_t n, std::size_t min_chunk, int workers, Body&& body) {
    if (n == 0) return;
    if (workers == 1) {
        body(std::size_t{0}, n);
        return;
    }
    // parallel_for uses min(num_threads, n / min_chunk) workers, so a chunk of at least
    // floor(n / workers) items caps the count at `workers` (rounding the chunk up
    // instead would give n / chunk = workers - 1 for most n: one thread for an odd n
    // and workers = 2).
    if (workers > 1)
        min_chunk = std::max<std::size_t>(min_chunk, n / static_cast<std::size_t>(workers));
    parallel_for(n, min_chunk, std::forward<Body>(body));
}

}  // namespace tpscore

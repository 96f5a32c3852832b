// A static kd-tree over 3D points: nearest, k-nearest and radius queries.
#pragma once

#include <cstdint>
#include <utility>
#include <vector>

#include "tpscore/types.hpp"

namespace tpscore {

/// Static kd-tree over a copy of (n, 3) points. Immutable after construction, so
/// concurrent queries from several threads are safe.
class KDTree {
public:
    /// Builds the tree. Preconditions: points finite; leaf_size >= 1.
    explicit KDTree(const PointsRef& points, int leaf_size = 16);

    /// Number of indexed points.
    std::int64_t size() const;

    /// The k nearest neighbours of each row of `queries` (m, 3), nearest first.
    /// Writes row-major (m, k) `distances` and `indices`; where fewer than k points lie
    /// within `max_distance`, the remaining slots get +inf and index -1.
    /// Threaded over query rows.
    void query(const PointsRef& queries, int k, double max_distance, double* distances,
               std::int64_t* indices) const;

    /// Appends (index, squared distance) of every point within `radius` of `query`
    /// (3 doubles) to `out`, in no particular order. Single-threaded; reentrant.
    void radius_search(const double* query, double radius,
                       std::vector<std::pair<std::int64_t, double>>& out) const;

    /// Batched radius query in CSR form: the neighbours of query i are
    /// indices[offsets[i] .. offsets[i+1]), with their distances; sorted by distance
    /// when `sort` is true. Threaded over query rows; output independent of threads.
    void query_radius(const PointsRef& queries, double radius, bool sort,
                      std::vector<std::int64_t>& offsets, std::vector<std::int64_t>& indices,
                      std::vector<double>& distances) const;

private:
    struct Node;
    Points points_;
    std::vector<std::int64_t> order_;
    std::vector<Node> nodes_;
    int leaf_size_;
};

}  // namespace tpscore

// Surface queries on a triangle mesh: closest point and ray casting, accelerated by a
// bounding-volume hierarchy (BVH) over the triangles.
#pragma once

#include <cstdint>
#include <vector>

#include "tpscore/types.hpp"

namespace tpscore {

/// The point of one triangle closest to a query point.
struct TrianglePoint {
    double point[3];        ///< the closest point
    double barycentric[3];  ///< its weights on the corners a, b, c (sum 1, each >= 0)
    double squared_distance;
};

/// Exact closest point of the triangle (a, b, c) to p (3 doubles each).
/// Classifies p into the Voronoi regions of the corners, edges and face of the triangle.
/// Degenerate triangles (zero or near-zero area) are treated as their three edges, so the
/// result is always finite for finite input.
TrianglePoint closest_point_on_triangle(const double* p, const double* a, const double* b,
                                        const double* c);

/// Intersection of the line o + t d with the triangle (a, b, c), boundary included.
/// Returns false when the line is parallel to the triangle's plane (to a relative 1e-12)
/// or the triangle is degenerate; otherwise true with t (in units of |d|) and the
/// barycentric weights u (of b) and v (of c), whether or not the hit lies inside the
/// triangle: callers check u >= 0, v >= 0, u + v <= 1.
bool intersect_line_triangle(const double* o, const double* d, const double* a, const double* b,
                             const double* c, double& t, double& u, double& v);

/// A triangle mesh prepared for closest-point and ray queries. Immutable after
/// construction, so concurrent queries from several threads are safe.
///
/// The BVH splits the triangles at the median centroid along the widest axis of their
/// centroids, down to leaves of `leaf_size` triangles (at most kMaxLeafSize); each
/// node's box bounds its triangles, padded by a tiny margin so that rounding never
/// hides a triangle that touches the box boundary. Every query is exact: it returns
/// what testing all triangles would, with ties (equal distance) going to the smaller
/// triangle index.
///
/// A closest-point query walks the tree collapsed to 8 children a node (all 8 boxes
/// tested at once), tests a leaf's triangles together, branch-free, in SIMD lanes
/// (the distance only; the point and its weights are computed once, for the winner),
/// and starts from the leaf that held the previous query's answer: for queries in
/// surface order (a grid, a mesh's vertices) the descent then has a tight bound from
/// its first step.
///
/// `workers` (every batched query): the number of threads to use; <= 0 means
/// tpscore::num_threads(); 1 runs serially.
class MeshSurface {
public:
    static constexpr int kMaxLeafSize = 8;

    /// Preconditions: vertices (nv, 3) finite; faces (nf, 3) with indices in [0, nv).
    MeshSurface(const PointsRef& vertices, const FacesRef& faces, int leaf_size = 8);

    /// The same triangles (`faces` as `shape` was built with) over moved `vertices`:
    /// `shape`'s tree with its boxes fitted again, a fraction of a build's cost. Queries
    /// stay exact whatever the motion; they slow down only as the motion scrambles
    /// the tree's grouping (a rigid or smooth motion keeps it).
    /// Preconditions: those of the other constructor, and faces equal to `shape`'s.
    MeshSurface(const MeshSurface& shape, const PointsRef& vertices, const FacesRef& faces);

    std::int64_t num_triangles() const { return static_cast<std::int64_t>(triangle_index_.size()); }

    /// For each row of `queries` (m, 3): the closest point of the mesh (m, 3 row-major
    /// `points`), its triangle (`triangles`, m), barycentric weights on that triangle's
    /// corners in face order (`barycentric`, m x 3) and the distance (`distances`, m).
    /// With no triangles, every output is NaN / -1. Threaded over query rows.
    void closest_point(const PointsRef& queries, double* points, std::int64_t* triangles,
                       double* barycentric, double* distances, int workers = 0) const;

    /// Casts the rays origins[i] + t directions[i] (m, 3 each; directions non-zero) and
    /// reports the nearest hit with 0 <= t <= max_distance, or with |t| <= max_distance
    /// (nearest by |t|) when `both_directions`. t is in units of |directions[i]|.
    /// Writes hit (m), t (m), points (m x 3), triangles (m), barycentric (m x 3);
    /// a miss writes false, NaN and -1. Rays parallel to a triangle do not hit it.
    /// Threaded over rays.
    void intersect_rays(const PointsRef& origins, const PointsRef& directions, double max_distance,
                        bool both_directions, bool* hit, double* t, double* points,
                        std::int64_t* triangles, double* barycentric, int workers = 0) const;

    struct Node {
        double lo[3];
        double hi[3];
        std::int32_t begin;  ///< first triangle (leaf order) of a leaf
        std::int32_t end;
        std::int32_t left;   ///< -1 for a leaf
        std::int32_t right;
    };

    /// The closest-point query's tree: the binary tree collapsed to up to kWide children
    /// per node, boxes stored one array per coordinate so that all children are tested
    /// at once in SIMD lanes. A child >= 0 is a WideNode; < 0 is the leaf Node -child - 1.
    static constexpr int kWide = 8;
    struct WideNode {
        double lo[3][kWide];  ///< unused slots hold an empty box (+inf, -inf)
        double hi[3][kWide];
        std::int32_t child[kWide];
        std::int32_t count;
    };

private:
    std::int32_t build(std::int32_t begin, std::int32_t end, const std::vector<double>& centroids);
    std::int32_t build_wide(std::int32_t node);
    void fit(const PointsRef& vertices, const FacesRef& faces);

    // Corners of each triangle in leaf order: 9 doubles (a, b, c) per triangle.
    std::vector<double> corners_;
    // The same triangles for the SIMD distance test: one block per leaf, holding each
    // quantity (closest_point.cpp, kTriangleFields) for kMaxLeafSize lanes, so that a
    // leaf's data is contiguous (a few cache lines, fetched together).
    std::vector<double> blocks_;
    // For each BVH node that is a leaf, its block; for each leaf-order triangle, the
    // BVH node of its leaf.
    std::vector<std::int32_t> block_of_;
    std::vector<std::int32_t> leaf_of_;
    std::vector<WideNode> wide_;
    std::vector<std::int64_t> triangle_index_;  // original index of each leaf-order triangle
    std::vector<Node> nodes_;
    double pad_ = 0.0;
    int leaf_size_;
};

}  // namespace tpscore

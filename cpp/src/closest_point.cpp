#include "tpscore/closest_point.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>

#include "tpscore/kdtree.hpp"  // parallel_rows
#include "tpscore/simd.hpp"

// The closest-point traversal is compiled for AVX-512, AVX2 and the baseline and
// picked at run time (TPSCORE_DISPATCH): its leaf test is a loop over a leaf's
// triangles that the compiler vectorises; the helpers are inlined into each build of
// the traversal (TPSCORE_INLINE), so they take its instruction set.

namespace tpscore {

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// A closest-point or ray query costs a few microseconds: 64 rows pay for a thread.
constexpr std::size_t kRowChunk = 64;

// A triangle whose corner angle at a has sin^2 below this is treated as its edges: the
// face formula divides by |ab x ac|^2, which rounding dominates for such slivers, while
// the edges are then within 1e-10 |ab| of the whole triangle.
constexpr double kDegenerateSin2 = 1e-20;

// A ray is parallel to a triangle when |d . (e1 x e2)| <= this * |d| |e1| |e2|.
constexpr double kParallelSin = 1e-12;

// Traversal stacks: median splits keep the BVH depth below 32 for any int32 count.
constexpr int kStackSize = 128;

inline double dot(const double* a, const double* b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

inline void sub(const double* a, const double* b, double* out) {
    out[0] = a[0] - b[0];
    out[1] = a[1] - b[1];
    out[2] = a[2] - b[2];
}

inline void cross(const double* a, const double* b, double* out) {
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

inline double squared_distance(const double* a, const double* b) {
    double d[3];
    sub(a, b, d);
    return dot(d, d);
}

// Fills `result` with the corner, edge point or face point given by weights (wa, wb, wc)
// and `point`, and its squared distance to p.
inline void set_result(TrianglePoint& result, const double* p, const double* point, double wa,
                       double wb, double wc) {
    for (int i = 0; i < 3; ++i) result.point[i] = point[i];
    result.barycentric[0] = wa;
    result.barycentric[1] = wb;
    result.barycentric[2] = wc;
    result.squared_distance = squared_distance(p, point);
}

// Closest point of the segment p0 + s (p1 - p0), s in [0, 1]; returns s.
inline double closest_on_segment(const double* p, const double* p0, const double* p1, double* point) {
    double e[3], rel[3];
    sub(p1, p0, e);
    sub(p, p0, rel);
    const double e2 = dot(e, e);
    double s = e2 > 0.0 ? dot(rel, e) / e2 : 0.0;
    s = std::min(1.0, std::max(0.0, s));
    for (int i = 0; i < 3; ++i) point[i] = p0[i] + s * e[i];
    return s;
}

// A degenerate triangle is the union of its edges: the closest of the three, first wins.
TrianglePoint closest_on_edges(const double* p, const double* a, const double* b, const double* c) {
    TrianglePoint best;
    double point[3];
    double s = closest_on_segment(p, a, b, point);
    set_result(best, p, point, 1.0 - s, s, 0.0);
    TrianglePoint other;
    s = closest_on_segment(p, b, c, point);
    set_result(other, p, point, 0.0, 1.0 - s, s);
    if (other.squared_distance < best.squared_distance) best = other;
    s = closest_on_segment(p, c, a, point);
    set_result(other, p, point, s, 0.0, 1.0 - s);
    if (other.squared_distance < best.squared_distance) best = other;
    return best;
}

// Squared distance from q to an axis-aligned box (0 inside).
inline double box_distance(const MeshSurface::Node& node, const double* q) {
    double d2 = 0.0;
    for (int a = 0; a < 3; ++a) {
        const double d = std::max(0.0, std::max(node.lo[a] - q[a], q[a] - node.hi[a]));
        d2 += d * d;
    }
    return d2;
}

// The ray's parameter interval inside the box, clipped to [t_min, t_max]; false when empty.
inline bool box_interval(const MeshSurface::Node& node, const double* o, const double* d,
                         const double* inv, double t_min, double t_max, double& t_enter,
                         double& t_exit) {
    for (int a = 0; a < 3; ++a) {
        if (d[a] == 0.0) {
            // Parallel to this slab: inside it for every t, or never.
            if (o[a] < node.lo[a] || o[a] > node.hi[a]) return false;
            continue;
        }
        double t0 = (node.lo[a] - o[a]) * inv[a];
        double t1 = (node.hi[a] - o[a]) * inv[a];
        if (t0 > t1) std::swap(t0, t1);
        t_min = std::max(t_min, t0);
        t_max = std::min(t_max, t1);
        if (t_min > t_max) return false;
    }
    t_enter = t_min;
    t_exit = t_max;
    return true;
}

// --- the vectorised closest-point query -----------------------------------------------

// What the SIMD test needs of each triangle (MeshSurface::blocks_): corner a, edges
// e0 = b - a and e1 = c - a, their dot products, and whether the triangle is
// degenerate (1) or not (0). A block holds kLanes values of each field in turn.
enum TriangleField { kAx, kAy, kAz, kE0x, kE0y, kE0z, kE1x, kE1y, kE1z, kE00, kE01, kE11, kDegenerate,
                     kTriangleFields };
constexpr int kLanes = MeshSurface::kMaxLeafSize;
constexpr std::size_t kBlockSize = kTriangleFields * kLanes;

// Squared distances from q to the kLanes triangles of a block, as
// closest_point_on_triangle classifies p (same regions, same order of precedence),
// written branch-free so that the loop runs in SIMD lanes: every region's weights are
// formed as numerator / denominator and the right pair is selected, so each lane
// divides once. A degenerate triangle's lane gives +infinity (the caller tests it
// with closest_point_on_triangle, as its edges). Lanes past a leaf's last triangle
// repeat it.
TPSCORE_INLINE void block_squared_distances(const double* block, const double* q, double* out) {
    const double* ax = block + kAx * kLanes;
    const double* ay = block + kAy * kLanes;
    const double* az = block + kAz * kLanes;
    const double* e0x = block + kE0x * kLanes;
    const double* e0y = block + kE0y * kLanes;
    const double* e0z = block + kE0z * kLanes;
    const double* e1x = block + kE1x * kLanes;
    const double* e1y = block + kE1y * kLanes;
    const double* e1z = block + kE1z * kLanes;
    const double* e00 = block + kE00 * kLanes;
    const double* e01 = block + kE01 * kLanes;
    const double* e11 = block + kE11 * kLanes;
    const double* degenerate = block + kDegenerate * kLanes;
    const double qx = q[0], qy = q[1], qz = q[2];
#pragma omp simd
    for (int i = 0; i < kLanes; ++i) {
        const double px = qx - ax[i], py = qy - ay[i], pz = qz - az[i];
        const double d1 = e0x[i] * px + e0y[i] * py + e0z[i] * pz;  // e0 . (p - a)
        const double d2 = e1x[i] * px + e1y[i] * py + e1z[i] * pz;  // e1 . (p - a)
        const double d3 = d1 - e00[i], d4 = d2 - e01[i];            // e0, e1 . (p - b)
        const double d5 = d1 - e01[i], d6 = d2 - e11[i];            // e0, e1 . (p - c)
        const double va = d3 * d6 - d5 * d4;
        const double vb = d5 * d2 - d1 * d6;
        const double vc = d1 * d4 - d3 * d2;
        // Inside the face, then each region that takes precedence over the ones before.
        double s = vb, t = vc, denominator = va + vb + vc;
        const bool bc = va <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0;
        s = bc ? d5 - d6 : s;
        t = bc ? d4 - d3 : t;
        denominator = bc ? (d4 - d3) + (d5 - d6) : denominator;
        const bool ac = vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0;
        s = ac ? 0.0 : s;
        t = ac ? d2 : t;
        denominator = ac ? d2 - d6 : denominator;
        const bool corner_c = d6 >= 0.0 && d5 <= d6;
        s = corner_c ? 0.0 : s;
        t = corner_c ? 1.0 : t;
        denominator = corner_c ? 1.0 : denominator;
        const bool ab = vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0;
        s = ab ? d1 : s;
        t = ab ? 0.0 : t;
        denominator = ab ? d1 - d3 : denominator;
        const bool corner_b = d3 >= 0.0 && d4 <= d3;
        s = corner_b ? 1.0 : s;
        t = corner_b ? 0.0 : t;
        denominator = corner_b ? 1.0 : denominator;
        const bool corner_a = d1 <= 0.0 && d2 <= 0.0;
        s = corner_a ? 0.0 : s;
        t = corner_a ? 0.0 : t;
        denominator = corner_a ? 1.0 : denominator;
        const double inverse = 1.0 / denominator;
        s *= inverse;
        t *= inverse;
        const double vx = px - s * e0x[i] - t * e1x[i];
        const double vy = py - s * e0y[i] - t * e1y[i];
        const double vz = pz - s * e0z[i] - t * e1z[i];
        const double squared = vx * vx + vy * vy + vz * vz;
        out[i] = degenerate[i] != 0.0 ? kInf : squared;
    }
}

struct BestTriangle {
    double squared_distance = kInf;
    std::int64_t index = -1;  // original triangle index
    std::int32_t slot = -1;   // leaf-order position
};

// The view of a MeshSurface that the query needs (its members are private).
struct SurfaceView {
    const MeshSurface::Node* nodes;
    const MeshSurface::WideNode* wide;
    std::size_t wide_count;
    const double* blocks;
    const std::int32_t* block_of;
    const double* corners;
    const std::int64_t* triangle_index;
    const std::int32_t* leaf_of;
};

// Offers the triangles of one leaf (BVH node `leaf`) to `best`: the SIMD distances,
// then the degenerate ones one by one. Ranking is by squared distance, then by
// original index.
TPSCORE_INLINE void test_leaf(const SurfaceView& surface, std::int32_t leaf, const double* q, BestTriangle& best) {
    const MeshSurface::Node& node = surface.nodes[leaf];
    const double* block = surface.blocks + kBlockSize * static_cast<std::size_t>(surface.block_of[leaf]);
    double squared[kLanes];
    block_squared_distances(block, q, squared);
    const std::int32_t slot_before = best.slot;
    for (std::int32_t i = node.begin; i < node.end; ++i) {
        const int lane = i - node.begin;
        double d2 = squared[lane];
        if (block[kDegenerate * kLanes + lane] != 0.0) {
            const double* tri = surface.corners + 9 * static_cast<std::size_t>(i);
            d2 = closest_point_on_triangle(q, tri, tri + 3, tri + 6).squared_distance;
        }
        const std::int64_t index = surface.triangle_index[i];
        if (d2 < best.squared_distance || (d2 == best.squared_distance && index < best.index)) {
            best.squared_distance = d2;
            best.index = index;
            best.slot = i;
        }
    }
    // The winner's corners are read again at the end of the query (the scalar
    // classification), from an array the traversal does not otherwise touch: fetch
    // them now, while the descent goes on, rather than stall on them then.
    if (best.slot != slot_before) {
        const char* corners = reinterpret_cast<const char*>(surface.corners + 9 * static_cast<std::size_t>(best.slot));
        __builtin_prefetch(corners);
        __builtin_prefetch(corners + 9 * sizeof(double) - 1);
    }
}

// Squared distances from q to the kWide boxes of a wide node (0 inside; +inf for an
// empty slot), in SIMD lanes.
TPSCORE_INLINE void child_box_distances(const MeshSurface::WideNode& node, const double* q, double* out) {
    const double qx = q[0], qy = q[1], qz = q[2];
#pragma omp simd
    for (int c = 0; c < MeshSurface::kWide; ++c) {
        // The distance outside the box along each axis, 0 inside (selects, not branches).
        const double bx = node.lo[0][c] - qx, ax = qx - node.hi[0][c];
        const double by = node.lo[1][c] - qy, ay = qy - node.hi[1][c];
        const double bz = node.lo[2][c] - qz, az = qz - node.hi[2][c];
        double dx = bx > ax ? bx : ax, dy = by > ay ? by : ay, dz = bz > az ? bz : az;
        dx = dx > 0.0 ? dx : 0.0;
        dy = dy > 0.0 ? dy : 0.0;
        dz = dz > 0.0 ? dz : 0.0;
        out[c] = dx * dx + dy * dy + dz * dz;
    }
}

// Closest points for query rows [row_begin, row_end).
TPSCORE_INLINE void closest_point_rows_impl(const SurfaceView& surface, const PointsRef& queries,
                                            std::size_t row_begin, std::size_t row_end, double* points,
                                            std::int64_t* triangles, double* barycentric, double* distances) {
    // Entries are wide nodes (>= 0) or leaves (< 0, as in WideNode::child).
    struct Entry {
        std::int32_t item;
        double d2;
    };
    Entry stack[kStackSize * MeshSurface::kWide];
    std::int32_t previous_leaf = -1;
    for (std::size_t r = row_begin; r < row_end; ++r) {
        const double q[3] = {queries(r, 0), queries(r, 1), queries(r, 2)};
        BestTriangle best;
        // The previous answer's leaf first: a tight bound before the descent.
        if (previous_leaf >= 0) test_leaf(surface, previous_leaf, q, best);
        int top = 0;
        if (surface.wide_count > 0) stack[top++] = Entry{0, 0.0};
        while (top > 0) {
            const Entry entry = stack[--top];
            // Strictly farther boxes only: a triangle at exactly the best distance may
            // still win the tie on its index.
            if (entry.d2 > best.squared_distance) continue;
            if (entry.item < 0) {
                const std::int32_t leaf = -entry.item - 1;
                if (leaf != previous_leaf) test_leaf(surface, leaf, q, best);
                continue;
            }
            const MeshSurface::WideNode& node = surface.wide[entry.item];
            double d2[MeshSurface::kWide];
            child_box_distances(node, q, d2);
            // Push the children within reach (without branches: whether a child is
            // within reach is data the branch predictor cannot learn), then swap the
            // nearest to the top so that it is searched first.
            // An empty slot's box is at +inf, but so is every box once a query is so far
            // away that its squared distance overflows; the slot count, not the distance,
            // keeps empty slots (whose child 0 is the root) off the stack.
            const int base = top;
            for (int c = 0; c < MeshSurface::kWide; ++c) {
                stack[top] = Entry{node.child[c], d2[c]};
                top += (c < node.count && d2[c] <= best.squared_distance) ? 1 : 0;
            }
            int nearest = base;
            for (int i = base + 1; i < top; ++i) nearest = stack[i].d2 < stack[nearest].d2 ? i : nearest;
            if (top > base) std::swap(stack[nearest], stack[top - 1]);
        }
        double* out_point = points + 3 * r;
        double* out_bary = barycentric + 3 * r;
        if (best.index < 0) {
            for (int i = 0; i < 3; ++i) out_point[i] = out_bary[i] = kNaN;
            distances[r] = kNaN;
            triangles[r] = -1;
            continue;
        }
        previous_leaf = surface.leaf_of[best.slot];
        // The winner's point and weights, by the scalar classification.
        const double* tri = surface.corners + 9 * static_cast<std::size_t>(best.slot);
        const TrianglePoint point = closest_point_on_triangle(q, tri, tri + 3, tri + 6);
        for (int i = 0; i < 3; ++i) {
            out_point[i] = point.point[i];
            out_bary[i] = point.barycentric[i];
        }
        distances[r] = std::sqrt(point.squared_distance);
        triangles[r] = best.index;
    }
}

TPSCORE_DISPATCH(closest_point_rows,
                 (const SurfaceView& surface, const PointsRef& queries, std::size_t row_begin, std::size_t row_end,
                  double* points, std::int64_t* triangles, double* barycentric, double* distances),
                 (surface, queries, row_begin, row_end, points, triangles, barycentric, distances))

}  // namespace

TrianglePoint closest_point_on_triangle(const double* p, const double* a, const double* b,
                                        const double* c) {
    double ab[3], ac[3], ap[3], n[3];
    sub(b, a, ab);
    sub(c, a, ac);
    cross(ab, ac, n);
    const double n2 = dot(n, n);
    if (!(n2 > kDegenerateSin2 * dot(ab, ab) * dot(ac, ac))) return closest_on_edges(p, a, b, c);

    TrianglePoint result;
    sub(p, a, ap);
    const double d1 = dot(ab, ap);
    const double d2 = dot(ac, ap);
    if (d1 <= 0.0 && d2 <= 0.0) {  // beyond corner a
        set_result(result, p, a, 1.0, 0.0, 0.0);
        return result;
    }
    double bp[3];
    sub(p, b, bp);
    const double d3 = dot(ab, bp);
    const double d4 = dot(ac, bp);
    if (d3 >= 0.0 && d4 <= d3) {  // beyond corner b
        set_result(result, p, b, 0.0, 1.0, 0.0);
        return result;
    }
    double point[3];
    const double vc = d1 * d4 - d3 * d2;
    if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) {  // outside edge ab, between a and b
        const double s = d1 / (d1 - d3);
        for (int i = 0; i < 3; ++i) point[i] = a[i] + s * ab[i];
        set_result(result, p, point, 1.0 - s, s, 0.0);
        return result;
    }
    double cp[3];
    sub(p, c, cp);
    const double d5 = dot(ab, cp);
    const double d6 = dot(ac, cp);
    if (d6 >= 0.0 && d5 <= d6) {  // beyond corner c
        set_result(result, p, c, 0.0, 0.0, 1.0);
        return result;
    }
    const double vb = d5 * d2 - d1 * d6;
    if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) {  // outside edge ac
        const double s = d2 / (d2 - d6);
        for (int i = 0; i < 3; ++i) point[i] = a[i] + s * ac[i];
        set_result(result, p, point, 1.0 - s, 0.0, s);
        return result;
    }
    const double va = d3 * d6 - d5 * d4;
    if (va <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0) {  // outside edge bc
        const double s = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        for (int i = 0; i < 3; ++i) point[i] = b[i] + s * (c[i] - b[i]);
        set_result(result, p, point, 0.0, 1.0 - s, s);
        return result;
    }
    // Inside the face: project onto the plane. The weights are ratios of signed areas,
    // computed as triple products with n (more accurate than va / (va + vb + vc), whose
    // denominator cancels badly for thin triangles).
    double t[3];
    cross(ap, ac, t);
    const double wb = dot(t, n) / n2;
    cross(ab, ap, t);
    const double wc = dot(t, n) / n2;
    for (int i = 0; i < 3; ++i) point[i] = a[i] + wb * ab[i] + wc * ac[i];
    set_result(result, p, point, 1.0 - wb - wc, wb, wc);
    return result;
}

bool intersect_line_triangle(const double* o, const double* d, const double* a, const double* b,
                             const double* c, double& t, double& u, double& v) {
    double e1[3], e2[3], pvec[3];
    sub(b, a, e1);
    sub(c, a, e2);
    cross(d, e2, pvec);
    const double det = dot(e1, pvec);
    const double scale = std::sqrt(dot(d, d) * dot(e1, e1) * dot(e2, e2));
    if (!(std::abs(det) > kParallelSin * scale)) return false;
    const double inv_det = 1.0 / det;
    double s[3], qvec[3];
    sub(o, a, s);
    u = dot(s, pvec) * inv_det;
    cross(s, e1, qvec);
    v = dot(d, qvec) * inv_det;
    t = dot(e2, qvec) * inv_det;
    return true;
}

MeshSurface::MeshSurface(const PointsRef& vertices, const FacesRef& faces, int leaf_size)
    : leaf_size_(std::clamp(leaf_size, 1, kMaxLeafSize)) {
    const auto nf = static_cast<std::int32_t>(faces.rows());
    std::vector<double> centroids(3 * static_cast<std::size_t>(nf));
    for (std::int32_t f = 0; f < nf; ++f)
        for (int i = 0; i < 3; ++i)
            centroids[3 * f + i] =
                (vertices(faces(f, 0), i) + vertices(faces(f, 1), i) + vertices(faces(f, 2), i)) / 3.0;
    triangle_index_.resize(static_cast<std::size_t>(nf));
    std::iota(triangle_index_.begin(), triangle_index_.end(), std::int64_t{0});
    if (nf > 0) {
        nodes_.reserve(static_cast<std::size_t>(2 * (nf / leaf_size_ + 1)));
        build(0, nf, centroids);
    }
    fit(vertices, faces);
}

MeshSurface::MeshSurface(const MeshSurface& shape, const PointsRef& vertices, const FacesRef& faces)
    : triangle_index_(shape.triangle_index_), nodes_(shape.nodes_), leaf_size_(shape.leaf_size_) {
    fit(vertices, faces);
}

// Everything but the tree's structure (nodes' ranges and children, the leaf order of
// the triangles): the corners in leaf order, the boxes, the SIMD blocks, the wide tree.
void MeshSurface::fit(const PointsRef& vertices, const FacesRef& faces) {
    const auto nf = static_cast<std::int32_t>(faces.rows());
    // The margin added to every box: far above the rounding of a box test or a
    // triangle-distance evaluation at the mesh's coordinate scale, far below anything
    // geometric.
    double scale = 1.0;
    for (std::int32_t f = 0; f < nf; ++f)
        for (int j = 0; j < 3; ++j)
            for (int i = 0; i < 3; ++i) scale = std::max(scale, std::abs(vertices(faces(f, j), i)));
    pad_ = 1e-9 * scale;

    corners_.resize(9 * static_cast<std::size_t>(nf));
    for (std::int32_t k = 0; k < nf; ++k) {
        const auto f = static_cast<Eigen::Index>(triangle_index_[k]);
        for (int j = 0; j < 3; ++j)
            for (int i = 0; i < 3; ++i) corners_[9 * k + 3 * j + i] = vertices(faces(f, j), i);
    }
    // Boxes from the leaves up: a node's children come after it (build numbers them in
    // preorder), so one backward pass sees every child before its parent. An inner box
    // is the union of its children's (already padded) boxes.
    for (auto node = nodes_.rbegin(); node != nodes_.rend(); ++node) {
        if (node->left >= 0) {
            const Node& l = nodes_[static_cast<std::size_t>(node->left)];
            const Node& r = nodes_[static_cast<std::size_t>(node->right)];
            for (int a = 0; a < 3; ++a) {
                node->lo[a] = std::min(l.lo[a], r.lo[a]);
                node->hi[a] = std::max(l.hi[a], r.hi[a]);
            }
            continue;
        }
        for (int a = 0; a < 3; ++a) {
            node->lo[a] = kInf;
            node->hi[a] = -kInf;
        }
        for (std::int32_t i = node->begin; i < node->end; ++i) {
            const double* corner = &corners_[9 * static_cast<std::size_t>(i)];
            for (int j = 0; j < 3; ++j)
                for (int a = 0; a < 3; ++a) {
                    node->lo[a] = std::min(node->lo[a], corner[3 * j + a]);
                    node->hi[a] = std::max(node->hi[a], corner[3 * j + a]);
                }
        }
        for (int a = 0; a < 3; ++a) {
            node->lo[a] -= pad_;
            node->hi[a] += pad_;
        }
    }

    // The SIMD test's blocks (one per leaf, in leaf order), and each triangle's leaf.
    const auto stride = static_cast<std::size_t>(nf);
    leaf_of_.assign(stride, -1);
    block_of_.assign(nodes_.size(), -1);
    std::int32_t blocks = 0;
    for (std::size_t id = 0; id < nodes_.size(); ++id)
        if (nodes_[id].left < 0) block_of_[id] = blocks++;
    blocks_.assign(kBlockSize * static_cast<std::size_t>(blocks), 0.0);
    for (std::size_t id = 0; id < nodes_.size(); ++id) {
        const Node& leaf = nodes_[id];
        if (leaf.left >= 0) continue;
        double* block = blocks_.data() + kBlockSize * static_cast<std::size_t>(block_of_[id]);
        for (int lane = 0; lane < kLanes; ++lane) {
            // Lanes past the leaf's last triangle repeat it (same distance, same index).
            const std::int32_t f = std::min(leaf.begin + lane, leaf.end - 1);
            const double* a = corners_.data() + 9 * static_cast<std::size_t>(f);
            double e0[3], e1[3], normal[3];
            sub(a + 3, a, e0);
            sub(a + 6, a, e1);
            cross(e0, e1, normal);
            const double values[kTriangleFields] = {
                a[0], a[1], a[2], e0[0], e0[1], e0[2], e1[0], e1[1], e1[2], dot(e0, e0), dot(e0, e1), dot(e1, e1),
                // The same test as closest_point_on_triangle's.
                dot(normal, normal) > kDegenerateSin2 * dot(e0, e0) * dot(e1, e1) ? 0.0 : 1.0};
            for (int field = 0; field < kTriangleFields; ++field) block[field * kLanes + lane] = values[field];
            if (leaf.begin + lane < leaf.end) leaf_of_[static_cast<std::size_t>(f)] = static_cast<std::int32_t>(id);
        }
    }
    wide_.clear();
    if (!nodes_.empty()) {
        wide_.reserve(nodes_.size() / 4 + 1);
        build_wide(0);
    }
}

// Collapses the binary subtree at `node` into a wide node: its children are opened,
// the one with the most triangles first, until kWide children or only leaves remain.
// The root of a one-leaf tree becomes a wide node with that single leaf.
std::int32_t MeshSurface::build_wide(std::int32_t node) {
    std::int32_t children[kWide];
    int count = 0;
    if (nodes_[static_cast<std::size_t>(node)].left < 0) {
        children[count++] = node;
    } else {
        children[count++] = nodes_[static_cast<std::size_t>(node)].left;
        children[count++] = nodes_[static_cast<std::size_t>(node)].right;
    }
    while (count < kWide) {
        int widest = -1;
        for (int c = 0; c < count; ++c) {
            const Node& child = nodes_[static_cast<std::size_t>(children[c])];
            if (child.left >= 0 &&
                (widest < 0 || child.end - child.begin >
                                   nodes_[static_cast<std::size_t>(children[widest])].end -
                                       nodes_[static_cast<std::size_t>(children[widest])].begin))
                widest = c;
        }
        if (widest < 0) break;
        const Node& opened = nodes_[static_cast<std::size_t>(children[widest])];
        children[widest] = opened.left;
        children[count++] = opened.right;
    }
    const auto id = static_cast<std::int32_t>(wide_.size());
    wide_.emplace_back();
    WideNode wide{};
    wide.count = count;
    for (int c = 0; c < kWide; ++c) {
        for (int a = 0; a < 3; ++a) {
            wide.lo[a][c] = kInf;
            wide.hi[a][c] = -kInf;
        }
        wide.child[c] = 0;
    }
    for (int c = 0; c < count; ++c) {
        const Node& child = nodes_[static_cast<std::size_t>(children[c])];
        for (int a = 0; a < 3; ++a) {
            wide.lo[a][c] = child.lo[a];
            wide.hi[a][c] = child.hi[a];
        }
        wide.child[c] = child.left < 0 ? -children[c] - 1 : build_wide(children[c]);
    }
    wide_[static_cast<std::size_t>(id)] = wide;
    return id;
}

std::int32_t MeshSurface::build(std::int32_t begin, std::int32_t end,
                                const std::vector<double>& centroids) {
    const auto id = static_cast<std::int32_t>(nodes_.size());
    nodes_.emplace_back();
    Node node;
    node.begin = begin;
    node.end = end;
    node.left = node.right = -1;
    if (end - begin > leaf_size_) {
        // Split at the median centroid along the widest axis of the centroids' extent.
        double clo[3] = {kInf, kInf, kInf}, chi[3] = {-kInf, -kInf, -kInf};
        for (std::int32_t i = begin; i < end; ++i) {
            const double* c = &centroids[3 * triangle_index_[i]];
            for (int a = 0; a < 3; ++a) {
                clo[a] = std::min(clo[a], c[a]);
                chi[a] = std::max(chi[a], c[a]);
            }
        }
        int axis = 0;
        for (int a = 1; a < 3; ++a)
            if (chi[a] - clo[a] > chi[axis] - clo[axis]) axis = a;
        const std::int32_t mid = begin + (end - begin) / 2;
        // The keys beside their triangles, so that the selection compares and moves
        // contiguous pairs instead of looking each centroid up (2-3 times faster).
        thread_local std::vector<std::pair<double, std::int64_t>> keyed;
        keyed.resize(static_cast<std::size_t>(end - begin));
        for (std::int32_t i = begin; i < end; ++i)
            keyed[i - begin] = {centroids[3 * triangle_index_[i] + axis], triangle_index_[i]};
        std::nth_element(keyed.begin(), keyed.begin() + (mid - begin), keyed.end(),
                         [](const auto& x, const auto& y) { return x.first < y.first; });
        for (std::int32_t i = begin; i < end; ++i) triangle_index_[i] = keyed[i - begin].second;
        node.left = build(begin, mid, centroids);
        node.right = build(mid, end, centroids);
    }
    // the boxes are fitted afterwards (fit), from the leaves up
    nodes_[static_cast<std::size_t>(id)] = node;
    return id;
}

void MeshSurface::closest_point(const PointsRef& queries, double* points, std::int64_t* triangles,
                                double* barycentric, double* distances, int workers) const {
    const SurfaceView surface{nodes_.data(),   wide_.data(),           wide_.size(),   blocks_.data(),
                              block_of_.data(), corners_.data(), triangle_index_.data(), leaf_of_.data()};
    const auto m = static_cast<std::size_t>(queries.rows());
    parallel_rows(m, kRowChunk, workers, [&](std::size_t row_begin, std::size_t row_end) {
        closest_point_rows(surface, queries, row_begin, row_end, points, triangles, barycentric, distances);
    });
}

void MeshSurface::intersect_rays(const PointsRef& origins, const PointsRef& directions,
                                 double max_distance, bool both_directions, bool* hit, double* t,
                                 double* points, std::int64_t* triangles, double* barycentric,
                                 int workers) const {
    const auto m = static_cast<std::size_t>(origins.rows());
    parallel_rows(m, kRowChunk, workers, [&](std::size_t row_begin, std::size_t row_end) {
        struct Entry {
            std::int32_t node;
            double key;  // the smallest |t| (or t) at which the ray can meet the box
        };
        Entry stack[kStackSize];
        for (std::size_t r = row_begin; r < row_end; ++r) {
            const double o[3] = {origins(r, 0), origins(r, 1), origins(r, 2)};
            const double d[3] = {directions(r, 0), directions(r, 1), directions(r, 2)};
            const double inv[3] = {1.0 / d[0], 1.0 / d[1], 1.0 / d[2]};
            // Hits are ranked by key = t (one direction) or |t| (both), then by index.
            double best_key = max_distance;
            double best_t = kNaN, best_u = kNaN, best_v = kNaN;
            std::int64_t best_index = -1;
            std::int32_t best_slot = -1;  // leaf-order position of the best triangle
            auto interval = [&](const Node& node, double& key) {
                const double lo = both_directions ? -best_key : 0.0;
                double enter, exit;
                if (!box_interval(node, o, d, inv, lo, best_key, enter, exit)) return false;
                key = both_directions ? (enter <= 0.0 && exit >= 0.0 ? 0.0
                                                                     : std::min(std::abs(enter), std::abs(exit)))
                                      : enter;
                return true;
            };
            int top = 0;
            double root_key;
            if (!nodes_.empty() && interval(nodes_[0], root_key)) stack[top++] = Entry{0, root_key};
            while (top > 0) {
                const Entry entry = stack[--top];
                if (entry.key > best_key) continue;
                const Node& node = nodes_[static_cast<std::size_t>(entry.node)];
                if (node.left < 0) {
                    for (std::int32_t i = node.begin; i < node.end; ++i) {
                        const double* tri = corners_.data() + 9 * static_cast<std::size_t>(i);
                        double th, u, v;
                        if (!intersect_line_triangle(o, d, tri, tri + 3, tri + 6, th, u, v)) continue;
                        if (!(u >= 0.0 && v >= 0.0 && u + v <= 1.0)) continue;
                        if (!both_directions && th < 0.0) continue;
                        const double key = both_directions ? std::abs(th) : th;
                        const std::int64_t index = triangle_index_[static_cast<std::size_t>(i)];
                        if (key < best_key || (key == best_key && (best_index < 0 || index < best_index))) {
                            best_key = key;
                            best_t = th;
                            best_u = u;
                            best_v = v;
                            best_index = index;
                            best_slot = i;
                        }
                    }
                    continue;
                }
                Entry near{node.left, 0.0}, far{node.right, 0.0};
                const bool near_ok = interval(nodes_[static_cast<std::size_t>(node.left)], near.key);
                const bool far_ok = interval(nodes_[static_cast<std::size_t>(node.right)], far.key);
                if (near_ok && far_ok && far.key < near.key) std::swap(near, far);
                if (near_ok && far_ok) {
                    stack[top++] = far;
                    stack[top++] = near;
                } else if (near_ok) {
                    stack[top++] = near;
                } else if (far_ok) {
                    stack[top++] = far;
                }
            }
            double* out_point = points + 3 * r;
            double* out_bary = barycentric + 3 * r;
            if (best_index < 0) {
                hit[r] = false;
                t[r] = kNaN;
                triangles[r] = -1;
                for (int i = 0; i < 3; ++i) out_point[i] = out_bary[i] = kNaN;
                continue;
            }
            hit[r] = true;
            t[r] = best_t;
            triangles[r] = best_index;
            out_bary[0] = 1.0 - best_u - best_v;
            out_bary[1] = best_u;
            out_bary[2] = best_v;
            // From the weights rather than o + t d: the reported point lies on the triangle.
            const double* tri = corners_.data() + 9 * static_cast<std::size_t>(best_slot);
            for (int i = 0; i < 3; ++i)
                out_point[i] = out_bary[0] * tri[i] + out_bary[1] * tri[3 + i] + out_bary[2] * tri[6 + i];
        }
    });
}

}  // namespace tpscore

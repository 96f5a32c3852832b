#include "tpscore/kdtree.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <numeric>

namespace tpscore {

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

// A query costs about a microsecond; a chunk of this many rows outweighs the tens of
// microseconds a thread costs to start.
constexpr std::size_t kQueryChunk = 512;

// Radius queries are collected per block of rows so that each block writes its own
// buffers and the blocks concatenate in row order whatever the thread count.
constexpr std::size_t kRadiusBlock = 256;

inline double squared_distance(const double* a, const double* b) {
    const double dx = a[0] - b[0];
    const double dy = a[1] - b[1];
    const double dz = a[2] - b[2];
    return dx * dx + dy * dy + dz * dz;
}

// Squared distance from q to the box [lo, hi] (0 inside).
inline double box_distance(const KDTree::Node& node, const double* q) {
    double d2 = 0.0;
    for (int a = 0; a < 3; ++a) {
        const double below = node.lo[a] - q[a];
        const double above = q[a] - node.hi[a];
        const double d = std::max(0.0, std::max(below, above));
        d2 += d * d;
    }
    return d2;
}

// Squared distance from q to the farthest corner of the box.
inline double box_farthest(const KDTree::Node& node, const double* q) {
    double d2 = 0.0;
    for (int a = 0; a < 3; ++a) {
        const double d = std::max(std::abs(q[a] - node.lo[a]), std::abs(node.hi[a] - q[a]));
        d2 += d * d;
    }
    return d2;
}

struct Candidate {
    double d2;
    std::int64_t index;
};

// Ranking used everywhere: distance first, then the original index, which makes the
// k nearest a uniquely defined set.
inline bool ranks_before(double d2, std::int64_t index, const Candidate& c) {
    return d2 < c.d2 || (d2 == c.d2 && index < c.index);
}

// The best k candidates so far, kept sorted in a fixed array: for small k an insertion
// into a short sorted run beats a heap and needs no allocation.
class SortedCandidates {
public:
    static constexpr int kCapacity = 64;

    explicit SortedCandidates(int k) : k_(k) {}

    bool full() const { return count_ == k_; }
    const Candidate& worst() const { return items_[count_ - 1]; }

    void offer(double d2, std::int64_t index) {
        if (full()) {
            if (!ranks_before(d2, index, worst())) return;
            --count_;
        }
        int i = count_++;
        while (i > 0 && ranks_before(d2, index, items_[i - 1])) {
            items_[i] = items_[i - 1];
            --i;
        }
        items_[i] = Candidate{d2, index};
    }

    void write(double* distances, std::int64_t* indices) const {
        for (int i = 0; i < k_; ++i) {
            if (i < count_) {
                distances[i] = std::sqrt(items_[i].d2);
                indices[i] = items_[i].index;
            } else {
                distances[i] = kInf;
                indices[i] = -1;
            }
        }
    }

private:
    std::array<Candidate, kCapacity> items_;
    int k_;
    int count_ = 0;
};

// Large k: a binary max-heap (worst on top) in a reusable buffer.
class HeapCandidates {
public:
    HeapCandidates(int k, std::vector<Candidate>& buffer) : k_(k), heap_(buffer) { heap_.clear(); }

    bool full() const { return static_cast<int>(heap_.size()) == k_; }
    const Candidate& worst() const { return heap_.front(); }

    void offer(double d2, std::int64_t index) {
        if (full()) {
            if (!ranks_before(d2, index, worst())) return;
            std::pop_heap(heap_.begin(), heap_.end(), worse_first);
            heap_.back() = Candidate{d2, index};
        } else {
            heap_.push_back(Candidate{d2, index});
        }
        std::push_heap(heap_.begin(), heap_.end(), worse_first);
    }

    void write(double* distances, std::int64_t* indices) {
        std::sort_heap(heap_.begin(), heap_.end(), worse_first);
        const int count = static_cast<int>(heap_.size());
        for (int i = 0; i < k_; ++i) {
            if (i < count) {
                distances[i] = std::sqrt(heap_[i].d2);
                indices[i] = heap_[i].index;
            } else {
                distances[i] = kInf;
                indices[i] = -1;
            }
        }
    }

private:
    // Heap order "a below b": a ranks before b, so the top is the worst candidate.
    static bool worse_first(const Candidate& a, const Candidate& b) {
        return ranks_before(a.d2, a.index, b);
    }
    int k_;
    std::vector<Candidate>& heap_;
};

}  // namespace

KDTree::KDTree(const PointsRef& points, int leaf_size)
    : leaf_size_(std::max(1, leaf_size)) {
    const std::int64_t n = points.rows();
    order_.resize(static_cast<std::size_t>(n));
    std::iota(order_.begin(), order_.end(), std::int64_t{0});
    points_ = points;  // the build reads the original order through order_
    if (n > 0) {
        nodes_.reserve(static_cast<std::size_t>(2 * (n / leaf_size_ + 1)));
        build(0, n);
    }
    // Permute into leaf order so that each leaf scans contiguous memory.
    Points permuted(n, 3);
    for (std::int64_t i = 0; i < n; ++i) permuted.row(i) = points_.row(order_[i]);
    points_.swap(permuted);
}

std::int64_t KDTree::size() const { return points_.rows(); }

std::int32_t KDTree::build(std::int64_t begin, std::int64_t end) {
    const auto id = static_cast<std::int32_t>(nodes_.size());
    nodes_.emplace_back();
    Node node;
    for (int a = 0; a < 3; ++a) {
        node.lo[a] = kInf;
        node.hi[a] = -kInf;
    }
    for (std::int64_t i = begin; i < end; ++i) {
        const double* p = points_.data() + 3 * order_[i];
        for (int a = 0; a < 3; ++a) {
            node.lo[a] = std::min(node.lo[a], p[a]);
            node.hi[a] = std::max(node.hi[a], p[a]);
        }
    }
    node.begin = begin;
    node.end = end;
    node.left = node.right = -1;
    if (end - begin > leaf_size_) {
        int axis = 0;
        for (int a = 1; a < 3; ++a)
            if (node.hi[a] - node.lo[a] > node.hi[axis] - node.lo[axis]) axis = a;
        const std::int64_t mid = begin + (end - begin) / 2;
        const double* coords = points_.data();
        std::nth_element(order_.begin() + begin, order_.begin() + mid, order_.begin() + end,
                         [coords, axis](std::int64_t a, std::int64_t b) {
                             return coords[3 * a + axis] < coords[3 * b + axis];
                         });
        node.left = build(begin, mid);
        node.right = build(mid, end);
    }
    nodes_[static_cast<std::size_t>(id)] = node;
    return id;
}

template <class Candidates>
void KDTree::search_knn(std::int32_t id, const double* q, double bound2, Candidates& best) const {
    const Node& node = nodes_[static_cast<std::size_t>(id)];
    if (node.left < 0) {
        const double* p = points_.data();
        for (std::int64_t i = node.begin; i < node.end; ++i) {
            const double d2 = squared_distance(q, p + 3 * i);
            if (d2 < bound2) best.offer(d2, order_[static_cast<std::size_t>(i)]);
        }
        return;
    }
    std::int32_t first = node.left;
    std::int32_t second = node.right;
    double d_first = box_distance(nodes_[static_cast<std::size_t>(first)], q);
    double d_second = box_distance(nodes_[static_cast<std::size_t>(second)], q);
    if (d_second < d_first) {
        std::swap(first, second);
        std::swap(d_first, d_second);
    }
    // A box is skipped only when it lies strictly farther than the current worst: a point
    // at exactly that distance could still win on the index tie-break.
    auto worth_visiting = [&](double d2) {
        return d2 < bound2 && !(best.full() && d2 > best.worst().d2);
    };
    if (worth_visiting(d_first)) search_knn(first, q, bound2, best);
    if (worth_visiting(d_second)) search_knn(second, q, bound2, best);
}

void KDTree::query(const PointsRef& queries, int k, double max_distance, double* distances,
                   std::int64_t* indices, int workers) const {
    const auto m = static_cast<std::size_t>(queries.rows());
    const std::size_t kk = static_cast<std::size_t>(k);
    // Only points strictly closer than max_distance count; inf * inf stays inf.
    const double bound2 = max_distance * max_distance;
    const bool empty = nodes_.empty();
    parallel_rows(m, kQueryChunk, workers, [&](std::size_t begin, std::size_t end) {
        std::vector<Candidate> buffer;
        if (k > SortedCandidates::kCapacity)
            buffer.reserve(std::min<std::size_t>(kk, static_cast<std::size_t>(size())));
        for (std::size_t r = begin; r < end; ++r) {
            const double q[3] = {queries(r, 0), queries(r, 1), queries(r, 2)};
            double* row_d = distances + r * kk;
            std::int64_t* row_i = indices + r * kk;
            if (k <= SortedCandidates::kCapacity) {
                SortedCandidates best(k);
                if (!empty && box_distance(nodes_[0], q) < bound2) search_knn(0, q, bound2, best);
                best.write(row_d, row_i);
            } else {
                HeapCandidates best(k, buffer);
                if (!empty && box_distance(nodes_[0], q) < bound2) search_knn(0, q, bound2, best);
                best.write(row_d, row_i);
            }
        }
    });
}

template <class Whole, class Each>
void KDTree::visit_radius(const double* query, double radius, std::int64_t whole_below, Whole&& whole,
                          Each&& each) const {
    if (nodes_.empty()) return;
    const double r2 = radius * radius;
    // An explicit stack: the tree depth is about log2(n / leaf_size), far below 64 for
    // any point set that fits in memory.
    std::int32_t stack[128];
    int top = 0;
    stack[top++] = 0;
    const double* p = points_.data();
    while (top > 0) {
        const Node& node = nodes_[static_cast<std::size_t>(stack[--top])];
        if (box_distance(node, query) > r2) continue;
        if (node.end - node.begin <= whole_below || box_farthest(node, query) <= r2) {
            // The whole box lies inside the ball (or is small enough to be counted
            // whole): no point needs a test.
            whole(node);
            continue;
        }
        if (node.left < 0) {
            for (std::int64_t i = node.begin; i < node.end; ++i) {
                const double d2 = squared_distance(query, p + 3 * i);
                if (d2 <= r2) each(i, d2);
            }
            continue;
        }
        stack[top++] = node.right;
        stack[top++] = node.left;
    }
}

void KDTree::radius_search(const double* query, double radius,
                           std::vector<std::pair<std::int64_t, double>>& out) const {
    const double* p = points_.data();
    visit_radius(
        query, radius, 0,
        [&](const Node& node) {
            // the distances of a box inside the ball are still reported
            for (std::int64_t i = node.begin; i < node.end; ++i)
                out.emplace_back(order_[static_cast<std::size_t>(i)], squared_distance(query, p + 3 * i));
        },
        [&](std::int64_t i, double d2) { out.emplace_back(order_[static_cast<std::size_t>(i)], d2); });
}

std::int64_t KDTree::radius_count(const double* query, double radius, std::int64_t whole_below) const {
    std::int64_t count = 0;
    visit_radius(
        query, radius, whole_below, [&](const Node& node) { count += node.end - node.begin; },
        [&](std::int64_t, double) { ++count; });
    return count;
}

void KDTree::count_radius(const PointsRef& queries, double radius, std::int64_t* counts,
                          int workers, std::int64_t whole_below) const {
    const auto m = static_cast<std::size_t>(queries.rows());
    parallel_rows(m, kQueryChunk, workers, [&](std::size_t begin, std::size_t end) {
        for (std::size_t r = begin; r < end; ++r) {
            const double q[3] = {queries(r, 0), queries(r, 1), queries(r, 2)};
            counts[r] = radius_count(q, radius, whole_below);
        }
    });
}

RadiusNeighbours KDTree::query_radius(const PointsRef& queries, double radius, bool sort, int workers) const {
    const auto m = static_cast<std::size_t>(queries.rows());
    const std::size_t blocks = (m + kRadiusBlock - 1) / kRadiusBlock;
    std::vector<std::vector<std::pair<std::int64_t, double>>> found(blocks);
    RadiusNeighbours result;
    IndexVector& offsets = result.offsets;
    offsets.setZero(static_cast<Eigen::Index>(m + 1));
    // Blocks are the unit of work; two blocks already pay for a thread.
    parallel_rows(blocks, 2, workers, [&](std::size_t block_begin, std::size_t block_end) {
        for (std::size_t b = block_begin; b < block_end; ++b) {
            auto& out = found[b];
            const std::size_t row_end = std::min(m, (b + 1) * kRadiusBlock);
            for (std::size_t r = b * kRadiusBlock; r < row_end; ++r) {
                const double q[3] = {queries(r, 0), queries(r, 1), queries(r, 2)};
                const std::size_t start = out.size();
                radius_search(q, radius, out);
                if (sort)
                    std::sort(out.begin() + static_cast<std::ptrdiff_t>(start), out.end(),
                              [](const auto& a, const auto& b2) {
                                  return a.second < b2.second ||
                                         (a.second == b2.second && a.first < b2.first);
                              });
                offsets[r + 1] = static_cast<std::int64_t>(out.size() - start);
            }
        }
    });
    for (std::size_t r = 0; r < m; ++r) offsets[r + 1] += offsets[r];
    const auto total = static_cast<Eigen::Index>(offsets[m]);
    result.indices.resize(total);
    result.distances.resize(total);
    Eigen::Index pos = 0;
    for (auto& out : found) {
        for (const auto& [index, d2] : out) {
            result.indices[pos] = index;
            result.distances[pos] = std::sqrt(d2);
            ++pos;
        }
        out.clear();
        out.shrink_to_fit();
    }
    return result;
}

}  // namespace tpscore

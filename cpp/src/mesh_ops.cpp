#include "tpscore/mesh_ops.hpp"

#include <Eigen/Geometry>
#include <algorithm>
#include <cfloat>
#include <cmath>
#include <limits>
#include <utility>
#include <vector>

#include "tpscore/parallel.hpp"

namespace tpscore {

namespace {

using Vec3 = Eigen::Vector3d;

// Below these sizes a loop runs on the calling thread: a few thousand cheap rows
// take less time than starting a thread.
constexpr std::size_t kFaceChunk = 8192;
constexpr std::size_t kVertexChunk = 4096;

// A weighted sum of unit normals shorter than this fraction of the total weight has
// cancelled to rounding noise (a few ulps per term), far below any real normal.
constexpr double kCancellation = 1e-12;

Vec3 vertex(const PointsRef& vertices, std::int64_t i) {
    return Vec3(vertices(i, 0), vertices(i, 1), vertices(i, 2));
}

bool collapsed(const FacesRef& faces, std::int64_t f) {
    return faces(f, 0) == faces(f, 1) || faces(f, 1) == faces(f, 2) ||
           faces(f, 0) == faces(f, 2);
}

// The clamped cotangent described beside kMaxCotangent.
double clamped_cotangent(double dot, double cross_norm) {
    return dot / std::max({cross_norm, std::abs(dot) / kMaxCotangent, DBL_MIN});
}

// Per-face quantities the per-vertex gathers need, computed once per face. Each
// array is filled only when asked for (atan2 alone costs more than the rest of a
// face, and every (m, 3) array written is memory the kernel has to touch). Eigen
// arrays are left uninitialised, so their pages are first touched by the threads.
struct FaceGeometry {
    bool with_cross = false, with_cotangents = false, with_voronoi = false, with_angles = false;
    Points cross;       // (m, 3) (x1 - x0) x (x2 - x0): twice the area times the unit normal
    Points cotangents;  // (m, 3) clamped cotangent of the angle at each corner
    Points voronoi;     // (m, 3) mixed Voronoi area given to each corner
    Points angles;      // (m, 3) corner angles, radians
};

void compute_face_geometry(const PointsRef& vertices, const FacesRef& faces, FaceGeometry& g) {
    const std::int64_t m = faces.rows();
    if (g.with_cross) g.cross.resize(m, 3);
    if (g.with_cotangents) g.cotangents.resize(m, 3);
    if (g.with_voronoi) g.voronoi.resize(m, 3);
    if (g.with_angles) g.angles.resize(m, 3);
    parallel_for(static_cast<std::size_t>(m), kFaceChunk, [&](std::size_t begin, std::size_t end) {
        for (std::size_t fu = begin; fu < end; ++fu) {
            const auto f = static_cast<std::int64_t>(fu);
            if (collapsed(faces, f)) {  // contributes nothing
                if (g.with_cross) g.cross.row(f).setZero();
                if (g.with_cotangents) g.cotangents.row(f).setZero();
                if (g.with_voronoi) g.voronoi.row(f).setZero();
                if (g.with_angles) g.angles.row(f).setZero();
                continue;
            }
            const Vec3 p[3] = {vertex(vertices, faces(f, 0)), vertex(vertices, faces(f, 1)),
                               vertex(vertices, faces(f, 2))};
            const Vec3 cross = (p[1] - p[0]).cross(p[2] - p[0]);
            const double double_area = cross.norm();  // |a x b| is the same at every corner
            if (g.with_cross) g.cross.row(f) = cross;
            double dot[3], cotangent[3];
            for (int k = 0; k < 3; ++k) {
                dot[k] = (p[(k + 1) % 3] - p[k]).dot(p[(k + 2) % 3] - p[k]);
                cotangent[k] = clamped_cotangent(dot[k], double_area);
                if (g.with_cotangents) g.cotangents(f, k) = cotangent[k];
                if (g.with_angles) g.angles(f, k) = std::atan2(double_area, dot[k]);
            }
            if (!g.with_voronoi) continue;
            const double area = 0.5 * double_area;
            const bool obtuse = dot[0] < 0 || dot[1] < 0 || dot[2] < 0;
            for (int k = 0; k < 3; ++k) {
                if (obtuse) {
                    g.voronoi(f, k) = dot[k] < 0 ? area / 2 : area / 4;
                } else {
                    // Voronoi region of corner k: the two half-edges from k, each times
                    // the cotangent of the angle opposite it, over 8.
                    const int j = (k + 1) % 3, l = (k + 2) % 3;
                    g.voronoi(f, k) = ((p[k] - p[j]).squaredNorm() * cotangent[l] +
                                       (p[k] - p[l]).squaredNorm() * cotangent[j]) /
                                      8.0;
                }
            }
        }
    });
}

// Vertex -> incident faces in CSR form; entry = 3 * face + corner, in face order.
// Collapsed faces are left out, so they contribute to no vertex.
struct Incidence {
    std::vector<std::int64_t> offsets;  // (n + 1,)
    std::vector<std::int64_t> corners;  // 3 * face + corner of each incidence
};

Incidence incidence(std::int64_t n, const FacesRef& faces) {
    Incidence inc;
    inc.offsets.assign(static_cast<std::size_t>(n) + 1, 0);
    const std::int64_t m = faces.rows();
    for (std::int64_t f = 0; f < m; ++f) {
        if (collapsed(faces, f)) continue;
        for (int c = 0; c < 3; ++c) ++inc.offsets[static_cast<std::size_t>(faces(f, c)) + 1];
    }
    for (std::size_t i = 0; i < static_cast<std::size_t>(n); ++i) inc.offsets[i + 1] += inc.offsets[i];
    inc.corners.resize(static_cast<std::size_t>(inc.offsets.back()));
    std::vector<std::int64_t> cursor(inc.offsets.begin(), inc.offsets.end() - 1);
    for (std::int64_t f = 0; f < m; ++f) {
        if (collapsed(faces, f)) continue;
        for (int c = 0; c < 3; ++c)
            inc.corners[static_cast<std::size_t>(cursor[static_cast<std::size_t>(faces(f, c))]++)] =
                3 * f + c;
    }
    return inc;
}

// True if some neighbour in `neighbours` (two entries per incident face: the face's
// other two vertices) does not occur exactly twice, i.e. some edge at the vertex does
// not have exactly two faces. Sorts `neighbours` in place.
bool has_open_edge(std::vector<std::int64_t>& neighbours) {
    std::sort(neighbours.begin(), neighbours.end());
    for (std::size_t s = 0; s < neighbours.size();) {
        std::size_t e = s;
        while (e < neighbours.size() && neighbours[e] == neighbours[s]) ++e;
        if (e - s != 2) return true;
        s = e;
    }
    return false;
}

}  // namespace

Points face_normals(const PointsRef& vertices, const FacesRef& faces) {
    const std::int64_t m = faces.rows();
    Points normals(m, 3);
    parallel_for(static_cast<std::size_t>(m), kFaceChunk, [&](std::size_t begin, std::size_t end) {
        for (std::size_t f = begin; f < end; ++f) {
            const auto fi = static_cast<std::int64_t>(f);
            Vec3 cross = Vec3::Zero();
            if (!collapsed(faces, fi)) {
                const Vec3 p0 = vertex(vertices, faces(fi, 0));
                cross = (vertex(vertices, faces(fi, 1)) - p0).cross(vertex(vertices, faces(fi, 2)) - p0);
            }
            const double norm = cross.norm();
            normals.row(fi) = norm > 0 ? Vec3(cross / norm) : Vec3::Zero();
        }
    });
    return normals;
}

Points vertex_normals(const PointsRef& vertices, const FacesRef& faces, NormalWeighting weighting) {
    const std::int64_t n = vertices.rows();
    FaceGeometry g;
    g.with_cross = true;
    g.with_angles = weighting == NormalWeighting::angle;
    compute_face_geometry(vertices, faces, g);
    const Incidence inc = incidence(n, faces);
    Points normals(n, 3);
    parallel_for(static_cast<std::size_t>(n), kVertexChunk, [&](std::size_t begin, std::size_t end) {
        for (std::size_t i = begin; i < end; ++i) {
            Vec3 sum = Vec3::Zero();
            double total_weight = 0;  // sum of |contribution|
            for (std::int64_t e = inc.offsets[i]; e < inc.offsets[i + 1]; ++e) {
                const std::int64_t entry = inc.corners[static_cast<std::size_t>(e)];
                const std::int64_t f = entry / 3;
                const Vec3 cross = g.cross.row(f).transpose();
                const double norm = cross.norm();
                if (norm == 0) continue;
                double weight = norm;  // area: |cross| = twice the area, the 2 cancels below
                if (weighting == NormalWeighting::angle) weight = g.angles(f, entry % 3);
                if (weighting == NormalWeighting::uniform) weight = 1.0;
                sum += (weight / norm) * cross;
                total_weight += weight;
            }
            // Face normals that cancel (a fold, opposite faces) leave only rounding
            // noise, whose direction means nothing: such a vertex gets zero too.
            const double norm = sum.norm();
            normals.row(static_cast<std::int64_t>(i)) =
                norm > kCancellation * total_weight ? Vec3(sum / norm) : Vec3::Zero();
        }
    });
    return normals;
}

CsrMatrix cotan_laplacian(const PointsRef& vertices, const FacesRef& faces) {
    const std::int64_t n = vertices.rows();
    FaceGeometry g;
    g.with_cotangents = true;
    compute_face_geometry(vertices, faces, g);
    const Incidence inc = incidence(n, faces);

    // Two passes over the rows: the first counts each row's distinct neighbours (an
    // interior edge appears once from each of its two faces), the second writes the
    // row straight into place. Recomputing the small per-row sort is cheaper than a
    // scratch copy of the whole matrix.
    auto gather = [&](std::size_t i, std::vector<std::pair<std::int64_t, double>>& entries) {
        entries.clear();
        for (std::int64_t e = inc.offsets[i]; e < inc.offsets[i + 1]; ++e) {
            const std::int64_t entry = inc.corners[static_cast<std::size_t>(e)];
            const std::int64_t f = entry / 3;
            const int c = static_cast<int>(entry % 3), j = (c + 1) % 3, l = (c + 2) % 3;
            // Edge (i, x_j) is opposite corner l, edge (i, x_l) opposite corner j.
            entries.emplace_back(faces(f, j), 0.5 * g.cotangents(f, l));
            entries.emplace_back(faces(f, l), 0.5 * g.cotangents(f, j));
        }
        // Sorting whole pairs also fixes the summation order of each merged entry.
        std::sort(entries.begin(), entries.end());
    };

    CsrMatrix result;
    result.size = n;
    result.indptr.resize(n + 1);
    result.indptr[0] = 0;
    parallel_for(static_cast<std::size_t>(n), kVertexChunk, [&](std::size_t begin, std::size_t end) {
        std::vector<std::pair<std::int64_t, double>> entries;
        for (std::size_t i = begin; i < end; ++i) {
            gather(i, entries);
            std::int64_t distinct = 0;
            for (std::size_t s = 0; s < entries.size(); ++s)
                distinct += (s == 0 || entries[s].first != entries[s - 1].first);
            result.indptr[static_cast<std::int64_t>(i) + 1] = distinct + 1;  // + the diagonal
        }
    });
    for (std::int64_t i = 0; i < n; ++i) result.indptr[i + 1] += result.indptr[i];
    const std::int64_t nnz = result.indptr[n];
    result.indices.resize(nnz);
    result.values.resize(nnz);

    parallel_for(static_cast<std::size_t>(n), kVertexChunk, [&](std::size_t begin, std::size_t end) {
        std::vector<std::pair<std::int64_t, double>> entries;
        for (std::size_t i = begin; i < end; ++i) {
            gather(i, entries);
            const auto row = static_cast<std::int64_t>(i);
            std::int64_t* out_index = result.indices.data() + result.indptr[row];
            double* out_value = result.values.data() + result.indptr[row];
            std::int64_t count = 0, diagonal = -1;
            double row_sum = 0;
            for (std::size_t s = 0; s < entries.size();) {
                const std::int64_t column = entries[s].first;
                double value = 0;
                for (; s < entries.size() && entries[s].first == column; ++s) value += entries[s].second;
                if (diagonal < 0 && column > row) diagonal = count++;  // keep columns sorted
                out_index[count] = column;
                out_value[count++] = value;
                row_sum += value;
            }
            if (diagonal < 0) diagonal = count++;
            out_index[diagonal] = row;
            out_value[diagonal] = -row_sum;
        }
    });
    return result;
}

VectorX voronoi_areas(const PointsRef& vertices, const FacesRef& faces) {
    const std::int64_t n = vertices.rows();
    FaceGeometry g;
    g.with_voronoi = true;
    compute_face_geometry(vertices, faces, g);
    const Incidence inc = incidence(n, faces);
    VectorX areas(n);
    parallel_for(static_cast<std::size_t>(n), kVertexChunk, [&](std::size_t begin, std::size_t end) {
        for (std::size_t i = begin; i < end; ++i) {
            double area = 0;
            for (std::int64_t e = inc.offsets[i]; e < inc.offsets[i + 1]; ++e) {
                const std::int64_t entry = inc.corners[static_cast<std::size_t>(e)];
                area += g.voronoi(entry / 3, entry % 3);
            }
            areas[static_cast<std::int64_t>(i)] = area;
        }
    });
    return areas;
}

BoolVector boundary_vertices(std::int64_t n_vertices, const FacesRef& faces) {
    const Incidence inc = incidence(n_vertices, faces);
    BoolVector boundary(n_vertices);
    parallel_for(static_cast<std::size_t>(n_vertices), kVertexChunk, [&](std::size_t begin, std::size_t end) {
        std::vector<std::int64_t> neighbours;
        for (std::size_t i = begin; i < end; ++i) {
            neighbours.clear();
            for (std::int64_t e = inc.offsets[i]; e < inc.offsets[i + 1]; ++e) {
                const std::int64_t entry = inc.corners[static_cast<std::size_t>(e)];
                const std::int64_t f = entry / 3;
                const int c = static_cast<int>(entry % 3);
                neighbours.push_back(faces(f, (c + 1) % 3));
                neighbours.push_back(faces(f, (c + 2) % 3));
            }
            boundary[static_cast<std::int64_t>(i)] = has_open_edge(neighbours);
        }
    });
    return boundary;
}

MeanCurvature mean_curvature(const PointsRef& vertices, const FacesRef& faces) {
    const std::int64_t n = vertices.rows();
    FaceGeometry g;
    g.with_cross = g.with_cotangents = g.with_voronoi = true;
    compute_face_geometry(vertices, faces, g);
    const Incidence inc = incidence(n, faces);
    MeanCurvature result;
    result.values.resize(n);
    result.normals.resize(n, 3);
    result.boundary.resize(n);
    constexpr double nan = std::numeric_limits<double>::quiet_NaN();
    parallel_for(static_cast<std::size_t>(n), kVertexChunk, [&](std::size_t begin, std::size_t end) {
        std::vector<std::int64_t> neighbours;
        for (std::size_t i = begin; i < end; ++i) {
            const auto row = static_cast<std::int64_t>(i);
            const Vec3 xi = vertex(vertices, row);
            Vec3 weighted_sum = Vec3::Zero();  // sum_j (cot a + cot b)(x_i - x_j)
            Vec3 normal = Vec3::Zero();        // area-weighted, for the sign only
            double area = 0;
            neighbours.clear();
            for (std::int64_t e = inc.offsets[i]; e < inc.offsets[i + 1]; ++e) {
                const std::int64_t entry = inc.corners[static_cast<std::size_t>(e)];
                const std::int64_t f = entry / 3;
                const int c = static_cast<int>(entry % 3), j = (c + 1) % 3, l = (c + 2) % 3;
                weighted_sum += g.cotangents(f, l) * (xi - vertex(vertices, faces(f, j))) +
                                g.cotangents(f, j) * (xi - vertex(vertices, faces(f, l)));
                normal += g.cross.row(f).transpose();
                area += g.voronoi(f, c);
                neighbours.push_back(faces(f, j));
                neighbours.push_back(faces(f, l));
            }
            const bool on_boundary = has_open_edge(neighbours);
            result.boundary[row] = on_boundary;
            if (on_boundary || !(area > 0)) {
                result.values[row] = nan;
                result.normals.row(row).setConstant(nan);
                continue;
            }
            const Vec3 k = weighted_sum / (2 * area);
            result.normals.row(row) = k;
            const double magnitude = 0.5 * k.norm();
            result.values[row] = k.dot(normal) >= 0 ? magnitude : -magnitude;
        }
    });
    return result;
}

Faces grid_triangles(const Eigen::Ref<const BoolVector>& valid, std::int64_t height, std::int64_t width) {
    // Serial: two passes over the quads (count, then write) cost far less than one
    // thread start, and a serial write keeps the row-major quad order for free.
    const auto quad_triangles = [&](std::int64_t a) {
        const int n = int{valid[a]} + int{valid[a + 1]} + int{valid[a + width]} + int{valid[a + width + 1]};
        return n == 4 ? 2 : (n == 3 ? 1 : 0);
    };
    std::int64_t count = 0;
    for (std::int64_t r = 0; r + 1 < height; ++r)
        for (std::int64_t c = 0; c + 1 < width; ++c) count += quad_triangles(r * width + c);
    Faces triangles(count, 3);
    std::int64_t t = 0;
    for (std::int64_t r = 0; r + 1 < height; ++r) {
        for (std::int64_t c = 0; c + 1 < width; ++c) {
            const std::int64_t a = r * width + c, b = a + 1, cc = a + width, d = a + width + 1;
            switch (quad_triangles(a)) {
                case 2:
                    triangles.row(t++) << a, cc, d;
                    triangles.row(t++) << a, d, b;
                    break;
                case 1:  // the three valid corners, winding as the full quad's halves
                    if (!valid[a]) triangles.row(t++) << cc, d, b;
                    else if (!valid[cc]) triangles.row(t++) << a, d, b;
                    else if (!valid[d]) triangles.row(t++) << a, cc, b;
                    else triangles.row(t++) << a, cc, d;
                    break;
                default:
                    break;
            }
        }
    }
    return triangles;
}

}  // namespace tpscore

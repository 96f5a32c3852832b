// Discrete differential operators on triangle meshes: normals, the cotangent
// Laplacian, mixed Voronoi areas and mean curvature (Meyer, Desbrun, Schroeder and
// Barr, "Discrete differential-geometry operators for triangulated 2-manifolds").
//
// Conventions shared by every function here:
// - vertices are (n, 3) row-major doubles; faces are (m, 3) int64 vertex indices,
//   every index in [0, n) (validated by the caller).
// - A face that repeats a vertex index ("collapsed") contributes nothing to any
//   per-vertex quantity and is ignored when edges are counted.
// - Cotangents are clamped to [-kMaxCotangent, kMaxCotangent] (see below), so
//   zero-area faces give large but finite weights, never inf or NaN.
// - Per-vertex results are gathered row by row over each vertex's incident faces in
//   face order, so they do not depend on the thread count.
#pragma once

#include <cstdint>

#include "tpscore/types.hpp"

namespace tpscore {

/// Bound on |cot| of a corner angle. The cotangent of a corner is
///   dot / max(|cross|, |dot| / kMaxCotangent, DBL_MIN),
/// with dot and cross of the corner's two edge vectors: for a zero-area face the
/// exact value is +-inf (or 0/0 at a corner with a zero-length edge); the clamp keeps
/// it finite and of the right sign, and a corner whose edges vanish gets 0. It only
/// acts on angles below about 1e-4 rad (0.006 degrees), which well-formed meshes never
/// have; the weights of such faces are large, so quantities next to them are not
/// meaningful, but they stay finite.
inline constexpr double kMaxCotangent = 1e4;

/// (n,) per-vertex flags.
using BoolVector = Eigen::Matrix<bool, Eigen::Dynamic, 1>;

/// Square sparse matrix in compressed sparse row form; the column indices of every
/// row are sorted and unique (the canonical form scipy.sparse expects).
struct CsrMatrix {
    std::int64_t size = 0;  ///< number of rows = number of columns
    IndexVector indptr;     ///< (size + 1,) row offsets into indices / values
    IndexVector indices;    ///< (nnz,) column of each stored entry
    VectorX values;         ///< (nnz,) value of each stored entry
};

/// How vertex_normals weights the unit normals of the faces around a vertex.
enum class NormalWeighting : int {
    area = 0,     ///< by face area (sum of the faces' cross products)
    angle = 1,    ///< by the face's corner angle at the vertex
    uniform = 2,  ///< every incident face counts once
};

/// Unit normal of each face, (m, 3), oriented by the right-hand rule over the face's
/// vertex order; zero for zero-area and collapsed faces.
Points face_normals(const PointsRef& vertices, const FacesRef& faces);

/// Unit normal of each vertex, (n, 3): the weighted sum of the unit normals of its
/// incident faces, normalised. Zero for a vertex in no face, in only zero-area faces,
/// or whose face normals cancel (sum shorter than 1e-12 times the total weight).
Points vertex_normals(const PointsRef& vertices, const FacesRef& faces,
                      NormalWeighting weighting);

/// Cotangent Laplacian, (n, n): L_ij = (cot alpha_ij + cot beta_ij) / 2 over the
/// angles opposite edge ij (one term on a boundary edge, one per face on a
/// non-manifold edge) and L_ii = -sum_{j != i} L_ij, so L is symmetric, negative
/// semi-definite on a well-shaped mesh, and L @ constant = 0. The diagonal is stored
/// for every vertex (0 for a vertex in no face).
CsrMatrix cotan_laplacian(const PointsRef& vertices, const FacesRef& faces);

/// Mixed Voronoi area of each vertex, (n,), in squared units: per incident
/// non-obtuse face its Voronoi region (Meyer et al., eq. 7); per obtuse face half
/// the face area at the obtuse corner and a quarter at the other two. The areas
/// of all vertices sum to the total face area.
VectorX voronoi_areas(const PointsRef& vertices, const FacesRef& faces);

/// Per vertex, (n,): true if the vertex lies on an edge that does not have exactly
/// two faces: an open-boundary edge (one face) or a non-manifold edge (three or
/// more). Collapsed faces are ignored. Vertices in no face are false.
/// Preconditions: every index in faces lies in [0, n_vertices).
BoolVector boundary_vertices(std::int64_t n_vertices, const FacesRef& faces);

/// Mean curvature of a triangle mesh at its vertices.
struct MeanCurvature {
    /// (n,) signed mean curvature H, 1/units; positive where the surface bends away
    /// from its outward (right-hand-rule) normal like a sphere: +1/R on a sphere of
    /// radius R with outward-oriented faces. NaN where undefined (see below).
    VectorX values;
    /// (n, 3) mean-curvature normal K = (1 / (2 A_i)) sum_j (cot a + cot b)(x_i - x_j)
    /// = 2 H n, 1/units. NaN where undefined.
    Points normals;
    /// (n,) the boundary_vertices mask.
    BoolVector boundary;
};

/// Mean curvature (Meyer et al.): K as above with A_i the mixed Voronoi area;
/// |H| = |K| / 2, with the sign of K . n for n the area-weighted vertex normal
/// (K . n >= 0 gives H >= 0). The one-ring formula only holds where the faces
/// around a vertex close into a disc, so values and normals are NaN on boundary
/// vertices and on vertices with zero Voronoi area (in no face, or only in
/// zero-area faces).
MeanCurvature mean_curvature(const PointsRef& vertices, const FacesRef& faces);

/// Triangles over the valid vertices of a height x width grid, as row-major flat
/// vertex indices (r * width + c). Each quad (r, c), (r, c+1), (r+1, c), (r+1, c+1)
/// whose four vertices are valid gives (a, c, d) and (a, d, b), split along its
/// (r, c)-(r+1, c+1) diagonal; a quad with exactly three valid vertices gives the one
/// triangle they form, wound the same way; quads in row-major order.
/// Preconditions: valid has height * width entries.
Faces grid_triangles(const Eigen::Ref<const BoolVector>& valid, std::int64_t height, std::int64_t width);

}  // namespace tpscore

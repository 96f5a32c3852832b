// Orthographic z-buffer rasterisation of triangle meshes, and reading images at
// continuous pixel positions.
#pragma once

#include <cstdint>

#include "tpscore/types.hpp"

namespace tpscore {

/// (n, 2) row-major point coordinates.
using Points2 = Eigen::Matrix<double, Eigen::Dynamic, 2, Eigen::RowMajor>;

/// Which triangle each pixel of an image sees, and where on it.
struct Raster {
    /// (height * width) triangle index per pixel, row after row; -1 where none covers it.
    IndexVector triangle;
    /// (height * width, 3) barycentric weights of the pixel centre on that triangle
    /// (0 where no triangle covers the pixel).
    MatrixX barycentric;
};

/// For each pixel of a width x height image, the front-most triangle covering the
/// pixel's centre.
///
/// pixels holds each vertex's continuous image position (x along the columns, y along
/// the rows; pixel (r, c) has its centre at (c + 0.5, r + 0.5)); depth is larger nearer
/// the viewer. A centre on a shared edge belongs to both triangles (a tolerance of 1e-9
/// in the barycentric weights closes hairline cracks); equal depths go to the lower
/// triangle index, so the result does not depend on the thread count. Zero-area
/// triangles cover nothing. Preconditions: faces index into pixels and depth; all
/// values finite.
///
/// Threads work on bands of rows, each over the triangles that reach into its band.
Raster rasterise(const Eigen::Ref<const Points2>& pixels, const Eigen::Ref<const VectorX>& depth,
                 const FacesRef& faces, std::int64_t width, std::int64_t height);

/// Values of each pixel's triangle, interpolated at its centre: row p of the result is
/// sum_k barycentric(p, k) * values(faces(triangle(p), k)), or NaN where triangle(p) is
/// -1. values is (n, c) row-major, one row per vertex; triangle and barycentric come
/// from rasterise(). Preconditions: triangle entries are -1 or index into faces, whose
/// entries index into values.
MatrixX interpolate_pixels(const MatrixRef& values, const FacesRef& faces,
                           const Eigen::Ref<const IndexVector>& triangle, const MatrixRef& barycentric);

/// Bilinear samples of a height x width image with `channels` values per pixel
/// (row-major, pixel centres at integers) at m continuous positions (x along the
/// columns, y along the rows), clamped to the image: out holds (m, channels) values.
/// The arithmetic is NumPy's for tpscore.reference.raster.bilinear step by step, in T
/// (float or double): fx = T(x - x0), then (a (1 - fx) + b fx) (1 - fy) + (...) fy,
/// each product rounded on its own (the file is built without fused multiply-adds), so
/// the two agree to the bit. Preconditions: height, width >= 2; x, y finite.
template <class T>
void bilinear_sample(const T* image, std::int64_t height, std::int64_t width, std::int64_t channels,
                     const double* x, const double* y, std::int64_t m, T* out);

}  // namespace tpscore

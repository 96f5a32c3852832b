#include "tpscore/raster.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "tpscore/parallel.hpp"

namespace tpscore {

namespace {

// Rows per band: a band's triangle list stays in cache, and a 500-row image still
// splits into enough bands to balance two to eight threads.
constexpr std::int64_t kBandRows = 16;
// Barycentric tolerance: a centre exactly on a shared edge must not fall between the
// two triangles through rounding.
constexpr double kInsideTolerance = -1e-9;

struct Box {
    std::int64_t c0, c1, r0, r1;  // inclusive pixel ranges; empty when c0 > c1 or r0 > r1
};

}  // namespace

Raster rasterise(const Eigen::Ref<const Points2>& pixels, const Eigen::Ref<const VectorX>& depth,
                 const FacesRef& faces, std::int64_t width, std::int64_t height) {
    const std::int64_t n_pixels = width * height;
    Raster out{IndexVector::Constant(n_pixels, -1), MatrixX::Zero(n_pixels, 3)};
    const std::int64_t n_faces = faces.rows();
    if (n_faces == 0 || n_pixels == 0) return out;

    // each triangle's pixel box (centres inside its bounding box), and the bands it reaches
    std::vector<Box> boxes(n_faces);
    const std::int64_t n_bands = (height + kBandRows - 1) / kBandRows;
    std::vector<std::vector<std::int64_t>> band_triangles(n_bands);
    for (std::int64_t t = 0; t < n_faces; ++t) {
        const auto a = faces(t, 0), b = faces(t, 1), c = faces(t, 2);
        const double xa = pixels(a, 0), xb = pixels(b, 0), xc = pixels(c, 0);
        const double ya = pixels(a, 1), yb = pixels(b, 1), yc = pixels(c, 1);
        const double area2 = (xb - xa) * (yc - ya) - (xc - xa) * (yb - ya);
        Box box{0, -1, 0, -1};
        if (std::abs(area2) >= 1e-12) {
            const double x_lo = std::min({xa, xb, xc}), x_hi = std::max({xa, xb, xc});
            const double y_lo = std::min({ya, yb, yc}), y_hi = std::max({ya, yb, yc});
            // centres c + 0.5 inside [lo, hi]; clamp before converting so that far-off
            // triangles cannot overflow the integer range
            auto first = [](double lo, std::int64_t n) {
                return static_cast<std::int64_t>(std::clamp(std::ceil(lo - 0.5), -1.0, double(n)));
            };
            auto last = [](double hi, std::int64_t n) {
                return static_cast<std::int64_t>(std::clamp(std::floor(hi - 0.5), -1.0, double(n)));
            };
            box = {std::max<std::int64_t>(first(x_lo, width), 0), std::min(last(x_hi, width), width - 1),
                   std::max<std::int64_t>(first(y_lo, height), 0), std::min(last(y_hi, height), height - 1)};
        }
        boxes[t] = box;
        if (box.c0 > box.c1 || box.r0 > box.r1) continue;
        for (std::int64_t band = box.r0 / kBandRows; band <= box.r1 / kBandRows; ++band)
            band_triangles[band].push_back(t);
    }

    parallel_for(static_cast<std::size_t>(n_bands), 1, [&](std::size_t band_begin, std::size_t band_end) {
        std::vector<double> zbuffer;
        for (std::size_t band = band_begin; band < band_end; ++band) {
            const std::int64_t row_begin = static_cast<std::int64_t>(band) * kBandRows;
            const std::int64_t row_end = std::min(height, row_begin + kBandRows);
            zbuffer.assign(static_cast<std::size_t>((row_end - row_begin) * width),
                           -std::numeric_limits<double>::infinity());
            // triangles arrive in increasing index order: a strict depth test keeps the
            // lower index on ties
            for (const std::int64_t t : band_triangles[band]) {
                const Box& box = boxes[t];
                const auto a = faces(t, 0), b = faces(t, 1), c = faces(t, 2);
                const double xa = pixels(a, 0), xb = pixels(b, 0), xc = pixels(c, 0);
                const double ya = pixels(a, 1), yb = pixels(b, 1), yc = pixels(c, 1);
                const double inv_area = 1.0 / ((xb - xa) * (yc - ya) - (xc - xa) * (yb - ya));
                const double za = depth(a), zb = depth(b), zc = depth(c);
                const std::int64_t r0 = std::max(box.r0, row_begin), r1 = std::min(box.r1, row_end - 1);
                for (std::int64_t r = r0; r <= r1; ++r) {
                    const double py = static_cast<double>(r) + 0.5;
                    for (std::int64_t col = box.c0; col <= box.c1; ++col) {
                        const double px = static_cast<double>(col) + 0.5;
                        const double w1 = ((px - xa) * (yc - ya) - (xc - xa) * (py - ya)) * inv_area;
                        const double w2 = ((xb - xa) * (py - ya) - (px - xa) * (yb - ya)) * inv_area;
                        const double w0 = 1.0 - w1 - w2;
                        if (w0 < kInsideTolerance || w1 < kInsideTolerance || w2 < kInsideTolerance) continue;
                        const double z = w0 * za + w1 * zb + w2 * zc;
                        double& best = zbuffer[static_cast<std::size_t>((r - row_begin) * width + col)];
                        if (!(z > best)) continue;
                        best = z;
                        const std::int64_t pixel = r * width + col;
                        out.triangle(pixel) = t;
                        out.barycentric(pixel, 0) = w0;
                        out.barycentric(pixel, 1) = w1;
                        out.barycentric(pixel, 2) = w2;
                    }
                }
            }
        }
    });
    return out;
}

MatrixX interpolate_pixels(const MatrixRef& values, const FacesRef& faces,
                           const Eigen::Ref<const IndexVector>& triangle, const MatrixRef& barycentric) {
    const std::int64_t n_pixels = triangle.size();
    const std::int64_t channels = values.cols();
    MatrixX out(n_pixels, channels);
    // pixels are independent rows; chunks of a few thousand keep thread start-up cheap
    parallel_for(static_cast<std::size_t>(n_pixels), 8192, [&](std::size_t begin, std::size_t end) {
        for (std::size_t p = begin; p < end; ++p) {
            const std::int64_t t = triangle(static_cast<std::int64_t>(p));
            if (t < 0) {
                out.row(p).setConstant(std::numeric_limits<double>::quiet_NaN());
                continue;
            }
            out.row(p) = barycentric(p, 0) * values.row(faces(t, 0)) + barycentric(p, 1) * values.row(faces(t, 1)) +
                         barycentric(p, 2) * values.row(faces(t, 2));
        }
    });
    return out;
}

template <class T>
void bilinear_sample(const T* image, std::int64_t height, std::int64_t width, std::int64_t channels,
                     const double* x, const double* y, std::int64_t m, T* out) {
    const T one = 1;
    // a few ns a sample: chunks of thousands keep thread start-up cheap
    parallel_for(static_cast<std::size_t>(m), 8192, [&](std::size_t begin, std::size_t end) {
        for (std::size_t i = begin; i < end; ++i) {
            const double xc = std::min(std::max(x[i], 0.0), static_cast<double>(width - 1));
            const double yc = std::min(std::max(y[i], 0.0), static_cast<double>(height - 1));
            const std::int64_t x0 = std::min(static_cast<std::int64_t>(std::floor(xc)), width - 2);
            const std::int64_t y0 = std::min(static_cast<std::int64_t>(std::floor(yc)), height - 2);
            const T fx = static_cast<T>(xc - static_cast<double>(x0));
            const T fy = static_cast<T>(yc - static_cast<double>(y0));
            const T* a = image + (y0 * width + x0) * channels;  // (y0, x0); b, c, d to its right and below
            const T* b = a + channels;
            const T* c = a + width * channels;
            const T* d = c + channels;
            T* row = out + static_cast<std::int64_t>(i) * channels;
            for (std::int64_t k = 0; k < channels; ++k) {
                const T top = a[k] * (one - fx) + b[k] * fx;
                const T bottom = c[k] * (one - fx) + d[k] * fx;
                row[k] = top * (one - fy) + bottom * fy;
            }
        }
    });
}

template void bilinear_sample<float>(const float*, std::int64_t, std::int64_t, std::int64_t, const double*,
                                     const double*, std::int64_t, float*);
template void bilinear_sample<double>(const double*, std::int64_t, std::int64_t, std::int64_t, const double*,
                                      const double*, std::int64_t, double*);

}  // namespace tpscore


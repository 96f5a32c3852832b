// nanobind glue for the z-buffer rasteriser and the bilinear image sampler
// (tpscore/raster.hpp). Inputs arrive validated from tpscore.raster (finite float64
// pixel positions and depths, int64 faces in range, a bounded image size); every
// result is an owning NumPy array (arrays.hpp).
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/stl/tuple.h>

#include <stdexcept>

#include "arrays.hpp"
#include "tpscore/raster.hpp"

namespace nb = nanobind;
using namespace nb::literals;
using tpscore_bindings::In;

namespace {
template <class T>
void bind_bilinear(nb::module_& m) {
    // An (h, w, c) image arrives as its (h * w, c) pixel rows.
    using Pixels = Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
    m.def(
        "bilinear_sample",
        [](In<Pixels> image, std::int64_t height, std::int64_t width, In<tpscore::VectorX> x,
           In<tpscore::VectorX> y) {
            if (height < 2 || width < 2) throw std::invalid_argument("the image needs at least 2 x 2 pixels");
            if (image.rows() != height * width) throw std::invalid_argument("the image needs height * width rows");
            if (y.size() != x.size()) throw std::invalid_argument("x and y differ in length");
            Pixels out(x.size(), image.cols());
            nb::gil_scoped_release release;
            tpscore::bilinear_sample<T>(image.data(), height, width, image.cols(), x.data(), y.data(), x.size(),
                                        out.data());
            return out;
        },
        "image"_a, "height"_a, "width"_a, "x"_a, "y"_a,
        "Bilinear samples (m, c) of an (h, w, c) image, given as (h * w, c), at (m,) positions x, y.");
}
}  // namespace

void bind_raster(nb::module_& m) {
    m.def(
        "rasterise",
        [](In<tpscore::Points2> pixels, In<tpscore::VectorX> depth, In<tpscore::Faces> faces, std::int64_t width,
           std::int64_t height) {
            tpscore::Raster raster = tpscore::rasterise(pixels, depth, faces, width, height);
            return std::make_tuple(std::move(raster.triangle), std::move(raster.barycentric));
        },
        "pixels"_a, "depth"_a, "faces"_a, "width"_a, "height"_a,
        nb::call_guard<nb::gil_scoped_release>(),
        "Front-most triangle (height * width,) and barycentric weights (height * width, 3) per pixel.");
    m.def(
        "interpolate_pixels",
        [](In<tpscore::MatrixX> values, In<tpscore::Faces> faces, In<tpscore::IndexVector> triangle,
           In<tpscore::MatrixX> barycentric) {
            return tpscore::interpolate_pixels(values, faces, triangle, barycentric);
        },
        "values"_a, "faces"_a, "triangle"_a, "barycentric"_a, nb::call_guard<nb::gil_scoped_release>(),
        "Vertex values (n, c) interpolated at each pixel's centre (pixels, c); NaN where no triangle.");
    bind_bilinear<float>(m);
    bind_bilinear<double>(m);
}

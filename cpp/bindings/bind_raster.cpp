// nanobind glue for the z-buffer rasteriser and the bilinear image sampler
// (tpscore/raster.hpp). Inputs arrive validated from tpscore.raster and
// tpscore.face.image (finite float64 pixel positions and depths, int64 faces in range,
// a bounded image size); the rasteriser returns owning NumPy arrays, the sampler fills
// an array Python allocated.
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/tuple.h>

#include <stdexcept>

#include "tpscore/raster.hpp"

namespace nb = nanobind;
using namespace nb::literals;

namespace {
template <class T>
void bind_bilinear(nb::module_& m) {
    using Image = nb::ndarray<const T, nb::ndim<3>, nb::c_contig, nb::device::cpu>;
    using Coordinates = nb::ndarray<const double, nb::ndim<1>, nb::c_contig, nb::device::cpu>;
    using Out = nb::ndarray<T, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
    m.def(
        "bilinear_sample_into",
        [](Image image, Coordinates x, Coordinates y, Out out) {
            const std::size_t m = x.shape(0);
            if (image.shape(0) < 2 || image.shape(1) < 2)
                throw std::invalid_argument("the image needs at least 2 x 2 pixels");
            if (y.shape(0) != m || out.shape(0) != m || out.shape(1) != image.shape(2))
                throw std::invalid_argument("x, y and out differ in length, or out in channels");
            nb::gil_scoped_release release;
            tpscore::bilinear_sample<T>(image.data(), static_cast<std::int64_t>(image.shape(0)),
                                        static_cast<std::int64_t>(image.shape(1)),
                                        static_cast<std::int64_t>(image.shape(2)), x.data(), y.data(),
                                        static_cast<std::int64_t>(m), out.data());
        },
        "image"_a.noconvert(), "x"_a.noconvert(), "y"_a.noconvert(), "out"_a.noconvert(),
        "Write bilinear samples of an (h, w, c) image at (m,) positions x, y into out (m, c).");
}
}  // namespace

void bind_raster(nb::module_& m) {
    m.def(
        "rasterise",
        [](const Eigen::Ref<const tpscore::Points2>& pixels, const Eigen::Ref<const tpscore::VectorX>& depth,
           const tpscore::FacesRef& faces, std::int64_t width, std::int64_t height) {
            tpscore::Raster raster = tpscore::rasterise(pixels, depth, faces, width, height);
            return std::make_tuple(std::move(raster.triangle), std::move(raster.barycentric));
        },
        "pixels"_a, "depth"_a, "faces"_a, "width"_a, "height"_a,
        nb::call_guard<nb::gil_scoped_release>(),
        "Front-most triangle (height * width,) and barycentric weights (height * width, 3) per pixel.");
    m.def("interpolate_pixels", &tpscore::interpolate_pixels, "values"_a, "faces"_a, "triangle"_a,
          "barycentric"_a, nb::call_guard<nb::gil_scoped_release>(),
          "Vertex values (n, c) interpolated at each pixel's centre (pixels, c); NaN where no triangle.");
    bind_bilinear<float>(m);
    bind_bilinear<double>(m);
}

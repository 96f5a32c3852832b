// nanobind glue for the z-buffer rasteriser (tpscore/raster.hpp). Inputs arrive
// validated from tpscore.raster (finite float64 pixel positions and depths, int64
// faces in range, a bounded image size); outputs are owning NumPy arrays.
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/stl/tuple.h>

#include "tpscore/raster.hpp"

namespace nb = nanobind;
using namespace nb::literals;

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
}

#include <nanobind/nanobind.h>

namespace nb = nanobind;

void bind_spatial(nb::module_& m) { (void)m; }

#include <nanobind/nanobind.h>

namespace nb = nanobind;

void bind_csrbf(nb::module_& m) { (void)m; }

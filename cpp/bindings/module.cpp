// The private extension tpscore._core. Each kernel family registers its own
// functions; validation and conversion happen in the Python layer beforehand.
#include <nanobind/nanobind.h>

#include "tpscore/parallel.hpp"
#include "tpscore/simd.hpp"

namespace nb = nanobind;

void bind_rbf(nb::module_& m);
void bind_csrbf(nb::module_& m);
void bind_spatial(nb::module_& m);
void bind_mesh_ops(nb::module_& m);
void bind_sparse_solve(nb::module_& m);
void bind_lattice_gram(nb::module_& m);
void bind_registration_terms(nb::module_& m);
void bind_raster(nb::module_& m);
void bind_skin_sim(nb::module_& m);

NB_MODULE(_core, m) {
    m.doc() = "tpscore's compiled kernels (private: use the tpscore package instead)";
    m.def("num_threads", &tpscore::num_threads, "Threads a kernel may use.");
    m.def("max_threads", &tpscore::max_threads,
          "The cap on the kernel thread count (4x the hardware threads).");
    m.def("set_num_threads", &tpscore::set_num_threads, nb::arg("n"),
          "Set the kernel thread count; n <= 0 restores the default, larger than "
          "max_threads() means max_threads().");
    m.def("simd_level", [] { return tpscore::simd_level_name(tpscore::simd_level()); },
          "The instruction set of the hand-dispatched kernels (TPSCORE_SIMD lowers it).");
    bind_rbf(m);
    bind_csrbf(m);
    bind_spatial(m);
    bind_mesh_ops(m);
    bind_sparse_solve(m);
    bind_lattice_gram(m);
    bind_registration_terms(m);
    bind_raster(m);
    bind_skin_sim(m);
}

"""Plain NumPy reference implementations of the compiled kernels, one module per
kernel family. They favour obvious correctness over speed; the tests compare the
compiled core against them and the benchmarks report the speed ratio."""

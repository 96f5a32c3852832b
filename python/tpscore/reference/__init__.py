"""Plain NumPy reference implementations of the compiled kernels, one module per
kernel family. They favour being obviously correct over speed or memory: tests
compare the compiled core against them, and benchmarks report the speed-up."""

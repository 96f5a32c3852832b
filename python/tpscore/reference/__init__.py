"""Plain NumPy reference implementations of the compiled kernels, one module per family.

They are slow and obviously correct; the tests compare the compiled core against them.
"""

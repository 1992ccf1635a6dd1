"""The float64 NumPy/SciPy reference of every kernel: the oracle of the tests, independent of
the kernels. Imports :mod:`clcurv._shared` only."""

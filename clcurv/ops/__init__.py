"""The operators on a DeviceCloud: the registry of methods, the one host driver of the
kernels, the features' device side, the scale space, the k-NN radius and the optimal
radius. Imports :mod:`clcurv.orient`, :mod:`clcurv.grid`, :mod:`clcurv.runtime`,
:mod:`clcurv.reference` and below."""

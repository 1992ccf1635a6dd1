"""clcurv: differential operators (normals, curvatures, MLS projections, scale space) on raw
3D point clouds, with OpenCL kernels and a float64 NumPy reference.

Reference: J. Digne, J.-M. Morel, *Numerical analysis of differential operators on raw point
clouds*, Numerische Mathematik 127 (2014), DOI 10.1007/s00211-013-0584-y.
"""
from clcurv.api.curvature import curvature, normals, project
from clcurv.api.features import features, FeatureResult
from clcurv.ops.registry import METHODS, OPERATORS
from clcurv.ops.smoothing import scale_space
from clcurv.jobs.job import curvature_file, features_file
from clcurv.grid.cloud import DeviceCloud
from clcurv.runtime.memory import release_memory
from clcurv.runtime.device import devices, get_device, NoDeviceError
from clcurv.runtime.program import BuildError, PrecisionError
from clcurv.api.result import CurvatureResult
from clcurv._shared.version import __version__
from clcurv import data, io, render
from clcurv.data import shapes

__all__ = ["curvature", "normals", "project", "features", "FeatureResult", "scale_space", "METHODS", "OPERATORS",
           "DeviceCloud", "release_memory", "devices", "get_device", "NoDeviceError", "BuildError",
           "PrecisionError", "CurvatureResult", "curvature_file", "features_file", "data", "io", "render", "shapes",
           "__version__"]

"""clcurv: differential operators (normals, curvatures, MLS projections, scale space) on raw
3D point clouds, with OpenCL kernels and a float64 NumPy reference.

Reference: J. Digne, J.-M. Morel, *Numerical analysis of differential operators on raw point
clouds*, Numerische Mathematik 127 (2014), DOI 10.1007/s00211-013-0584-y.
"""
from .api import curvature, normals, project
from .features import features, FeatureResult
from .operators import METHODS, OPERATORS
from .smoothing import scale_space
from .tiled import curvature_file
from .tiled_features import features_file
from .cloud import DeviceCloud
from .memory import release_memory
from .device import devices, get_device, NoDeviceError
from .program import BuildError, PrecisionError
from .result import CurvatureResult
from . import data, io, render, shapes

__version__ = "0.1.0"
__all__ = ["curvature", "normals", "project", "features", "FeatureResult", "scale_space", "METHODS", "OPERATORS",
           "DeviceCloud", "release_memory", "devices", "get_device", "NoDeviceError", "BuildError",
           "PrecisionError", "CurvatureResult", "curvature_file", "features_file", "data", "io", "render", "shapes",
           "__version__"]

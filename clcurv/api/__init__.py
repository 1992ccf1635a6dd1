"""The in-memory Python API: curvature, normals, project, features and their results.
Imports :mod:`clcurv.orient`, :mod:`clcurv.ops` and below."""

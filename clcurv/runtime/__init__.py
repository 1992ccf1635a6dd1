"""OpenCL devices, program builds and device memory: what any kernel launch needs. Imports
:mod:`clcurv._shared` only."""

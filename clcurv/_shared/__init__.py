"""The floor every other imports: constants shared with the kernels, argument checks, the host's
thread pool and host memory. Imports nothing of clcurv's."""

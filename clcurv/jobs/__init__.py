"""A run from files to files: the job the command line describes, in memory or in tiles (the one
place that decides). Imports :mod:`clcurv.tiles` and below."""

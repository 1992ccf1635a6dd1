"""Large clouds in tiles: planning, buckets on disk, the workspace, the engine, workers (Dask),
and the tiled scale space, orientation and features. Whether a run is made in tiles is
decided above, in :mod:`clcurv.jobs`. Imports :mod:`clcurv.api`, :mod:`clcurv.io` and
below."""

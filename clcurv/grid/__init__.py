"""The uniform grid: binning on the host, the DeviceCloud (points, records and cells on the
device) and the anchor frames. Imports :mod:`clcurv.runtime` and below."""

"""Normal orientation: towards a viewpoint or direction, and the spanning forest of a k-NN
graph (on the device). Imports :mod:`clcurv.grid` and below."""

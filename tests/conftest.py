"""Shared fixtures: the OpenCL devices (real kernels on PoCL, never mocked) and shapes."""
import numpy as np
import pytest

import clcurv


def _device_ids():
    try:
        return [d.index for d in clcurv.devices()]
    except Exception:  # no platform: every device test fails loudly below
        return []


DEVICES = _device_ids()


@pytest.fixture(params=DEVICES or [None], ids=lambda i: f"dev{i}")
def device(request):
    """Every OpenCL device present; fails (not skips) when there is none."""
    if request.param is None:
        pytest.fail("no OpenCL device found: " + clcurv.device.APT_HINT)
    return clcurv.get_device(request.param)


def bumpy_surface(n, seed, noise=0.002):
    """A smooth random height field z = 0.2 sin(3x) cos(2y) over [-1, 1]^2 with noise."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, (n, 2))
    z = 0.2 * np.sin(3 * xy[:, 0]) * np.cos(2 * xy[:, 1]) + noise * rng.normal(size=n)
    return np.column_stack([xy, z])


def worst(values, k=5):
    """The k worst entries with their indices, for assertion messages."""
    values = np.asarray(values)
    idx = np.argsort(values)[::-1][:k]
    return ", ".join(f"[{i}]={values[i]:.3g}" for i in idx)

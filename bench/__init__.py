"""Benchmarks of clcurv against its peers: run ``python -m bench.run`` (see bench/run.py)."""

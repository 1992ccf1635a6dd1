"""Benchmarks of clcurv against its peers (``python -m bench.run``, see bench/run.py), the
paper's experiments (``python -m bench.paper``) and the tolerances and targets they share
with the tests (bench/targets.py)."""

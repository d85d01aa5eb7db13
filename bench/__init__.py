"""Benchmarks and evaluation: `python -m bench [--quick]` writes `docs/benchmarks.md`."""

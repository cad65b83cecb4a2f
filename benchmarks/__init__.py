"""Benchmarks: each module runs as `python -m benchmarks.<name>` from the repository root and prints its
figures (results in benchmarks/results/). Inputs come from tests/factories/, evaluation helpers from
benchmarks/lib/evaluation.py.
"""
import stages  # noqa: F401  (before any benchmark imports torch: OMP_WAIT_POLICY, see stages/__init__.py)

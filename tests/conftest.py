"""Test session settings shared by every test module."""
import os

# Before torch loads libgomp (see dag.py): idle OpenMP threads sleep instead of spinning.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

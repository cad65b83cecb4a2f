"""Test session settings shared by every test module."""
import stages  # noqa: F401  (before any test imports torch: OMP_WAIT_POLICY, see stages/__init__.py)

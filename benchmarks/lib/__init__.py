"""The benchmarks' libraries: metrics (pose and mask scores, the sample's ground truth seen from a camera, boxes,
depth errors, cut scoring) and the helpers scripts share. Scripts (`benchmarks/<name>.py`) import these, never one
another; a library has no `main` and imports no script (tests/test_layout.py)."""

"""The extract stage: its settings and inputs (spec.py, light) and its run (run.py, loaded when a node runs)."""

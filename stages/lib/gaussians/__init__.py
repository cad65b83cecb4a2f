"""Gaussian splatting core: model, PLY I/O, projection, rasterizers and trainer (import-light: no torch here)."""

"""A capture's frames: reading videos within bounds and choosing the sharp, evenly spread frames."""

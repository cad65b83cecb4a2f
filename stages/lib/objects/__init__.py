"""Cutting the object out of a splatted scene: the ground plane it stands on (support), clusters, silhouettes
and point clouds."""

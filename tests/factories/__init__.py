"""Builders of stage inputs with known ground truth, shared by the tests and the benchmarks.

media: image and video files; orbits: an orbit video of a textured box scene (SfM registers it);
splats: Gaussian scenes and splat_train / extract / sfm output folders; backgrounds: background photos
with depth and planes; shapes: a small COCO dataset; runs: a stage's Context and short chains of stages.
"""

"""Builders of stage inputs with known ground truth, shared by the tests and the benchmarks.

media: image and video files; orbits: an orbit video of a textured box scene (SfM registers it);
splats: Gaussian scenes and splat_train / extract / sfm output folders; backgrounds: background photos
with depth and planes; shapes: a small COCO dataset; runs: a stage's Context and short chains of stages;
fuzz_*: the file readers fuzzed in child processes (seeds, cases, readers, the child); toy_cache: toy stages and
a driver process for the cache's fault tests.
"""

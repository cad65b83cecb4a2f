"""Each stage's spec, in a module named after the stage: its settings (`<Name>Config`, the Hydra structured
config of its section) and the inputs it reads (`INPUTS`, stages/inputs.py).

Specs import nothing heavy (no torch, Open3D, COLMAP or OpenCV), so the app composes and checks a config,
builds the graph, checks the input files and plans a run without loading the libraries the stages compute
with (`python dag.py` answers a wrong setting or a missing file in about a second); the stage module, which
does the work, is imported only when one of its nodes runs. A library whose settings a stage exposes (the
splat trainer's, the detector's, the cut's) takes its config dataclass from the spec as well.
"""

"""Cut-and-Splat stages: one module per pipeline stage, plus shared subpackages."""

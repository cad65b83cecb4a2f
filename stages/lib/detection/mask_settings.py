"""The settings of the mask post-processing (stages/lib/detection/postprocess.py), light: the eval stage's spec
takes them without loading torch (EvalConfig documents each)."""
from __future__ import annotations

from stages.contract.choices import choices

# eval.mask_score: how a detection's mask is ranked in the mask AP. "box": the box classifier's score, as
# torchvision gives it; "maskness": that score times the mean mask probability inside the mask (SOLOv2's
# maskness), so a mask the head is unsure of ranks below a crisp one of the same box score.
MaskScore = choices("MaskScore", ("box", "maskness"))
MASK_REFINE_EPS = 3e-4  # the guided filter's regulariser in squared colour units (eval.mask_refine_eps)

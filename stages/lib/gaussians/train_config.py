"""The settings of Gaussian-splat training and densification, and the rasterizer backends to choose from: plain
dataclasses (no torch), so that configs holding them load without the libraries that use them."""
from __future__ import annotations

from dataclasses import dataclass

from stages.contract.choices import choices

BACKENDS = ("auto", "torch", "cpp", "cuda", "gsplat")  # stages/lib/gaussians/rasterize.py says what each is
Backend = choices("Backend", BACKENDS)


@dataclass
class DensifyConfig:
    """Densification settings: those of 3DGS, with a Gaussian budget, a focus region and no opacity reset."""

    densify_from: int = 100
    densify_until: int = 1500
    densify_every: int = 100
    grad_threshold: float = 5e-4  # mean view-space (NDC) gradient norm that triggers clone / split (3DGS: 2e-4)
    max_growth: float = 0.3  # one densification adds at most this fraction of the current count
    percent_dense: float = 0.01  # clone below, split above this fraction of the scene extent
    prune_opacity: float = 0.005
    prune_scale: float = 0.1  # prune Gaussians larger than this fraction of the scene extent
    prune_screen: float = 0.25  # after the first opacity reset: prune radii above this x image long side
    opacity_reset_every: int = 0  # 0 disables; only while densifying, not in the last half period
    max_gaussians: int = 30000  # the sample plants' worst held-out cut IoU: 0.85-0.90 at 20k, 0.90-0.91 at 30k
    focus_radius: float = 0.6  # focus region: this x mean camera distance around the look-at point; 0 = all
    background_grad_threshold: float = 5e-4  # outside the focus region densify above this gradient; 0 = never
    # (the sample plant's striped wall: 23.2 -> 25.3 dB held-out; all objects then fill max_gaussians)


@dataclass
class TrainConfig(DensifyConfig):
    """Optimisation settings, and those of the densification strategy (DensifyConfig): 3DGS's with the
    schedule shortened to a few thousand iterations, the learning rates of means, scales and colour
    doubled to match, and no opacity reset."""

    iterations: int = 2000  # sample plant 25.3 dB held-out (23.9 with a 1700-iteration schedule)
    sh_degree: int = 3  # degree of the saved model
    sh_degree_every: int = 300  # raise the active SH degree by one every this many iterations
    lambda_dssim: float = 0.2
    lr_means: float = 3.2e-4  # x scene extent, decays exponentially to lr_means_final
    lr_means_final: float = 1.6e-5
    lr_sh_dc: float = 5e-3
    lr_sh_rest: float = 1.25e-4
    lr_opacity: float = 0.05
    lr_scales: float = 1e-2
    lr_quats: float = 1e-3
    eval_every: int = 100
    plateau_patience: int = 4  # evals without plateau_min_delta gain (after densification) -> stop
    plateau_min_delta: float = 0.05  # dB
    checkpoint_every: int = 500
    backend: Backend = Backend.auto  # rasterizer backend (stages/lib/gaussians/rasterize.py)

"""How monocular depth models get depth wrong, as a function to apply to true depth, set to a model's published
error (the degradation of benchmarks/mono_depth.py, whose docstring says why it is built this way).

relative: the inverse depth warped, blurred and noisy, then affine disparity (random scale and shift); metric:
the depth times a random global factor, warped, blurred and noisy. A knob k scales warp, edge blur and noise; the
edge blur has its own multiple; `calibrate` finds them for a published AbsRel and delta1.
"""
from __future__ import annotations

import logging
import math

import cv2
import numpy as np

log = logging.getLogger("benchmarks.lib.depth_degradation")

PUBLISHED = {"relative": {"abs_rel": 0.053, "delta1": 0.973}, "metric": {"abs_rel": 0.073, "delta1": 0.961}}
WARP, BLUR_PX, NOISE, SCALE_SIGMA = 0.08, 2.0, 0.02, 0.08  # per unit of k (blur at 640 px wide)
BLURS = (4.0, 8.0, 16.0, 32.0)  # edge blur multiples tried to match the published delta1 at its AbsRel


def smooth_field(height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """A low-frequency random field [H, W] of unit standard deviation: four plane waves of 0.3-1.2 cycles per width."""
    v, u = np.mgrid[0:height, 0:width] / width
    field = np.zeros((height, width))
    for _ in range(4):
        frequency = rng.uniform(0.3, 1.2)
        angle, phase = rng.uniform(0, 2 * np.pi, 2)
        field += np.cos(2 * np.pi * frequency * (u * np.cos(angle) + v * np.sin(angle)) + phase)
    return field / field.std()


def corrupt(values: np.ndarray, valid: np.ndarray, k: float, blur: float, rng: np.random.Generator) -> np.ndarray:
    """values [H, W] (inverse depth or depth) warped by exp(WARP k field), blurred by BLUR_PX k blur pixels (edges
    soften), plus correlated noise of NOISE k times the median; 0 outside `valid`."""
    height, width = values.shape
    out = values * np.exp(WARP * k * smooth_field(height, width, rng))
    sigma = BLUR_PX * k * blur * width / 640
    if sigma > 0:  # a blur of the valid pixels only: a sensor's holes do not pull their neighbours
        weight = cv2.GaussianBlur(valid.astype(np.float64), (0, 0), sigma)
        out = cv2.GaussianBlur(np.where(valid, out, 0.0), (0, 0), sigma) / np.maximum(weight, 1e-6)
    noise = cv2.GaussianBlur(rng.standard_normal((height, width)), (0, 0), 2.0)
    out = out + NOISE * k * float(np.median(values[valid])) * noise / max(noise.std(), 1e-9)
    return np.where(valid, out, 0.0)


def degrade(depth: np.ndarray, family: str, k: float, blur: float,
            rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """What a monocular model of `family` gives for true depth [H, W] (0 = none) at knob k with edge blur `blur`
    (corrupt): (disparity or metres [H, W] float32, 0 = none; the draws). Relative: affine disparity; metric:
    metres off by a global factor."""
    valid = depth > 0
    if family == "relative":
        inverse = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
        warped = corrupt(inverse / np.median(inverse[valid]), valid, k, blur, rng)
        scale, shift = math.exp(rng.uniform(math.log(0.1), math.log(10.0))), rng.uniform(-0.2, 0.5)
        disparity = np.where(valid, scale * (warped + shift), 0.0)
        return np.maximum(disparity, 0.0).astype(np.float32), {"scale": scale, "shift": shift}
    factor = math.exp(rng.normal(0.0, SCALE_SIGMA * k))
    metres = corrupt(depth * factor, valid, k, blur, rng)
    return np.maximum(metres, 0.0).astype(np.float32), {"factor": factor}


def depth_errors(estimate: np.ndarray, depth: np.ndarray, family: str) -> tuple[float, float]:
    """(AbsRel, delta1) of an estimate [H, W] against true depth [H, W], as the published figures are measured:
    relative disparity after its least-squares scale and shift fit to the true disparity, metric as it is."""
    valid = (depth > 0) & (estimate > 0)
    truth = depth[valid]
    if family == "relative":
        design = np.stack([estimate[valid], np.ones(valid.sum())], axis=1)
        (a, b), *_ = np.linalg.lstsq(design, 1.0 / truth, rcond=None)
        predicted = 1.0 / np.maximum(a * estimate[valid] + b, 1e-3)
    else:
        predicted = estimate[valid]
    ratio = np.maximum(predicted / truth, truth / predicted)
    return float(np.mean(np.abs(predicted - truth) / truth)), float(np.mean(ratio < 1.25))


def errors_at(depths: list[np.ndarray], family: str, k: float, blur: float, seed: int) -> tuple[float, float]:
    """Mean (AbsRel, delta1) over the true depths [H, W] degraded at (k, blur), the i-th with seed [seed, i]."""
    errors = [depth_errors(degrade(depth, family, k, blur, np.random.default_rng([seed, i]))[0], depth, family)
              for i, depth in enumerate(depths)]
    return float(np.mean([e[0] for e in errors])), float(np.mean([e[1] for e in errors]))


def knob_for(depths: list[np.ndarray], family: str, blur: float, abs_rel: float, seed: int) -> float:
    """The knob k at which the mean AbsRel of `family` (edge blur `blur`) over the depths is `abs_rel` (bisection)."""
    low, high = 0.0, 8.0
    for _ in range(12):
        middle = (low + high) / 2
        low, high = (middle, high) if errors_at(depths, family, middle, blur, seed)[0] < abs_rel else (low, middle)
    return (low + high) / 2


def calibrate(depths: list[np.ndarray], family: str, seed: int) -> dict[float, float]:
    """{edge blur: k} of `family`'s published level: for each edge blur of BLURS the k that gives the published
    AbsRel, the blur whose delta1 is nearest the published delta1 first."""
    published = PUBLISHED[family]
    fits = []
    for blur in BLURS:
        k = knob_for(depths, family, blur, published["abs_rel"], seed)
        fits.append((abs(errors_at(depths, family, k, blur, seed)[1] - published["delta1"]), blur, k))
        log.info("%s: edge blur x%g: k %.3f, delta1 off by %.3f", family, blur, k, fits[-1][0])
    return {blur: k for _, blur, k in sorted(fits)}

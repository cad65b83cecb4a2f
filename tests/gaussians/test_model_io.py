"""Gaussian model operations and file I/O (Inria PLY, .splat) on synthetic and real files."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from stages.contract.errors import StageError
from stages.lib.gaussians.model import SH_C0, Gaussians, quat_to_rotmat, rotmat_to_quat
from stages.lib.gaussians.ply import read_ply, read_splat, write_ply
from stages.lib.gaussians.sh import eval_sh



def random_gaussians(n: int = 50, degree: int = 3, seed: int = 0) -> Gaussians:
    gen = torch.Generator().manual_seed(seed)
    quats = torch.randn(n, 4, generator=gen)
    return Gaussians(
        means=torch.randn(n, 3, generator=gen),
        log_scales=torch.randn(n, 3, generator=gen) * 0.3 - 2.0,
        quats=quats / quats.norm(dim=1, keepdim=True),
        opacity_logits=torch.randn(n, generator=gen),
        sh=torch.randn(n, (degree + 1) ** 2, 3, generator=gen) * 0.5,
    )


def random_rotation(seed: int) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def test_ply_round_trip(tmp_path):
    g = random_gaussians(degree=3)
    write_ply(tmp_path / "g.ply", g)
    h = read_ply(tmp_path / "g.ply")
    assert h.num == g.num and h.sh_degree == 3
    for name in ("means", "log_scales", "opacity_logits", "sh"):
        assert torch.equal(getattr(h, name), getattr(g, name)), name
    torch.testing.assert_close(h.quats, g.quats, atol=1e-6, rtol=0)
    header = (tmp_path / "g.ply").read_bytes().split(b"end_header\n")[0].decode()
    assert "format binary_little_endian 1.0" in header and "property float f_rest_44" in header
    assert "property float f_rest_45" not in header


def test_ply_round_trip_degree0_and_bad_files(tmp_path):
    g = random_gaussians(n=7, degree=0)
    write_ply(tmp_path / "g0.ply", g)
    assert read_ply(tmp_path / "g0.ply").sh_degree == 0
    (tmp_path / "bad.ply").write_bytes(b"not a ply\n")
    with pytest.raises(StageError, match="bad.ply"):
        read_ply(tmp_path / "bad.ply")
    with pytest.raises(StageError, match="missing.ply"):
        read_ply(tmp_path / "missing.ply")
    (tmp_path / "odd.splat").write_bytes(b"\0" * 33)
    with pytest.raises(StageError, match="32-byte"):
        read_splat(tmp_path / "odd.splat")


def test_read_real_inria_ply(real):
    path = real / "plush_dog" / "inria_point_cloud.ply"
    g = read_ply(path)
    assert g.num == 15105 and g.sh_degree == 3
    assert torch.isfinite(g.means).all() and torch.isfinite(g.sh).all()
    torch.testing.assert_close(g.quats.norm(dim=1), torch.ones(g.num))
    # A trained model is mostly opaque small Gaussians with colours in a sane range.
    assert g.opacities.median() > 0.5
    assert 1e-4 < g.scales.median() < 0.1
    colours = 0.5 + SH_C0 * g.sh[:, 0]
    assert colours.median() > 0.0 and colours.median() < 1.0


def test_read_real_splat(real):
    path = real / "splats" / "plant.splat"
    g = read_splat(path)
    assert g.num == 113648 and g.sh_degree == 0
    raw = np.frombuffer(path.read_bytes()[:32], dtype=np.uint8)
    first = np.frombuffer(path.read_bytes()[:24], dtype="<f4")
    torch.testing.assert_close(g.means[0], torch.from_numpy(first[:3].copy()))
    torch.testing.assert_close(g.scales[0], torch.from_numpy(first[3:6].copy()))  # linear -> log -> exp
    rgba = raw[24:28].astype(np.float32) / 255.0
    torch.testing.assert_close(0.5 + SH_C0 * g.sh[0, 0], torch.from_numpy(rgba[:3]))
    torch.testing.assert_close(g.opacities[0], torch.tensor(float(rgba[3])), atol=1e-5, rtol=0)
    q = (raw[28:32].astype(np.float32) - 128.0) / 128.0
    torch.testing.assert_close(g.quats[0], torch.from_numpy(q / np.linalg.norm(q)))
    torch.testing.assert_close(g.quats.norm(dim=1), torch.ones(g.num))


def test_quaternion_conversions():
    for seed in range(5):
        rotation = random_rotation(seed)
        q = rotmat_to_quat(rotation)
        torch.testing.assert_close(quat_to_rotmat(q[None])[0], rotation)


def test_subset_cat_and_from_points():
    g = random_gaussians(n=10)
    part = g.subset(torch.arange(10) % 2 == 0)
    assert part.num == 5 and torch.equal(part.means, g.means[::2])
    assert Gaussians.cat([part, g.subset([1, 3])]).num == 7
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5]], dtype=np.float32)
    colours = np.array([[1, 0, 0]] * 5, dtype=np.float32)
    init = Gaussians.from_points(points, colours, sh_degree=2)
    assert init.sh_degree == 2 and init.num == 5
    torch.testing.assert_close(0.5 + SH_C0 * init.sh[:, 0], torch.from_numpy(colours))
    torch.testing.assert_close(init.opacities, torch.full((5,), 0.1))
    # The isolated point gets a much larger initial scale than the clustered ones.
    assert init.scales[4, 0] > 3 * init.scales[0, 0]
    with pytest.raises(ValueError):
        Gaussians(g.means, g.log_scales, g.quats, g.opacity_logits[:3], g.sh)


def test_transformed_positions_and_covariances():
    g = random_gaussians(n=40, degree=1)
    rotation, translation, scale = random_rotation(3), torch.tensor([0.3, -1.0, 2.0]), 2.5
    moved = g.transformed(rotation, translation, scale)
    r32 = rotation.float()
    torch.testing.assert_close(moved.means, scale * g.means @ r32.T + translation)
    torch.testing.assert_close(moved.covariances(), scale ** 2 * r32 @ g.covariances() @ r32.T,
                               atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(moved.opacity_logits, g.opacity_logits)
    # Composition: two transforms equal the composed one.
    rotation2, translation2, scale2 = random_rotation(4), torch.tensor([1.0, 0.0, -0.5]), 0.5
    twice = moved.transformed(rotation2, translation2, scale2)
    once = g.transformed(rotation2 @ rotation, scale2 * translation @ rotation2.float().T + translation2,
                         scale * scale2)
    for name in ("means", "log_scales", "sh"):
        torch.testing.assert_close(getattr(twice, name), getattr(once, name), atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(twice.covariances(), once.covariances(), atol=1e-6, rtol=1e-4)
    with pytest.raises(ValueError):
        g.transformed(torch.diag(torch.tensor([1.0, 1.0, -1.0])), translation, 1.0)


def test_transformed_rotates_view_dependent_colour():
    g = random_gaussians(n=30, degree=3)
    rotation = random_rotation(7)
    moved = g.transformed(rotation, torch.zeros(3), 1.7)
    dirs = torch.randn(30, 3, generator=torch.Generator().manual_seed(1))
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    # The colour the moved model shows along R d equals the original's colour along d.
    original = eval_sh(3, g.sh, dirs)
    rotated = eval_sh(3, moved.sh, dirs @ rotation.float().T)
    torch.testing.assert_close(rotated, original, atol=1e-4, rtol=1e-4)
    # And it is a real change: evaluating the unrotated coefficients along R d differs.
    assert (eval_sh(3, g.sh, dirs @ rotation.float().T) - original).abs().max() > 0.1
    torch.testing.assert_close(moved.sh[:, 0], g.sh[:, 0])


def test_with_sh_degree_and_device_ops():
    g = random_gaussians(n=4, degree=1)
    up = g.with_sh_degree(3)
    assert up.sh_degree == 3 and torch.equal(up.sh[:, :4], g.sh) and not up.sh[:, 4:].any()
    assert g.with_sh_degree(0).sh.shape == (4, 1, 3)
    assert math.isclose(float(g.detach().to("cpu").scales[0, 0]), float(torch.exp(g.log_scales[0, 0])))

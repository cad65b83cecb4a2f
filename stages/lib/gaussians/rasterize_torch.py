"""Pure-PyTorch tile rasterizer: the autograd reference the fast kernels are tested against.

Tiles are processed in chunks (tiles of similar Gaussian counts together, padded to the chunk's
largest count) so memory stays bounded; the compositing rules are those of 3DGS: front to back,
alpha = min(0.99, o * exp(-q / 2)), contributions with alpha < 1/255 skipped, and a pixel stops at
the first Gaussian that would bring its transmittance below 1e-4 (that Gaussian is not applied).
"""
from __future__ import annotations

import torch

from stages.lib.gaussians.binning import TILE_SIZE, TileBins
from stages.lib.gaussians.projection import ALPHA_MIN

ALPHA_MAX = 0.99
T_MIN = 1e-4
CHUNK_ELEMENTS = 1 << 22  # padded [tiles, gaussians, pixels] elements per chunk


def rasterize_tiles_torch(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                          features: torch.Tensor, bins: TileBins, width: int,
                          height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite per-Gaussian features front to back (no background).

    means2d [N, 2], conics [N, 3], opacities [N], features [N, F]. Returns
    (image [H, W, F] = sum_i f_i alpha_i T_i, transmittance [H, W] after the last Gaussian).
    """
    device, dtype = means2d.device, means2d.dtype
    num_feat = features.shape[1]
    offsets = bins.offsets.long()
    counts = offsets[1:] - offsets[:-1]  # [num_tiles]
    occupied = torch.nonzero(counts).squeeze(-1)
    occupied = occupied[torch.argsort(counts[occupied])]
    local = torch.arange(TILE_SIZE * TILE_SIZE, device=device)
    local_xy = torch.stack([local % TILE_SIZE, local // TILE_SIZE], dim=-1)  # [256, 2]

    sorted_counts = counts[occupied].tolist()

    pixel_chunks, feat_chunks, trans_chunks = [], [], []
    start = 0
    while start < len(sorted_counts):
        stop = start + 1  # counts ascend, so the last tile of a chunk sets its padding
        while (stop < len(sorted_counts)
               and (stop - start + 1) * sorted_counts[stop] * 256 <= CHUNK_ELEMENTS):
            stop += 1
        tiles = occupied[start:stop]  # [t]
        kmax = sorted_counts[stop - 1]
        slot = torch.arange(kmax, device=device)
        valid = slot < counts[tiles, None]  # [t, k]
        pair = torch.clamp(offsets[tiles, None] + slot, max=max(bins.gauss_ids.numel() - 1, 0))
        gid = bins.gauss_ids[pair].long()  # [t, k]
        origin = torch.stack([tiles % bins.tiles_x, tiles // bins.tiles_x], -1) * TILE_SIZE
        pix_xy = origin[:, None, :] + local_xy  # [t, 256, 2] integer pixel indices
        centre = pix_xy.to(dtype) + 0.5
        d = centre[:, None, :, :] - means2d[gid][:, :, None, :]  # [t, k, 256, 2]
        con = conics[gid]  # [t, k, 3]
        dx, dy = d[..., 0], d[..., 1]
        power = (-0.5 * (con[..., 0, None] * dx * dx + con[..., 2, None] * dy * dy)
                 - con[..., 1, None] * dx * dy)  # [t, k, 256]
        alpha = torch.clamp(opacities[gid][..., None] * torch.exp(power), max=ALPHA_MAX)
        used = valid[..., None] & (alpha >= ALPHA_MIN) & (power <= 0)
        alpha = torch.where(used, alpha, torch.zeros_like(alpha))
        with torch.no_grad():
            alive = torch.cumprod(1.0 - alpha, dim=1) >= T_MIN  # monotone: stops at first failure
        alpha = torch.where(alive, alpha, torch.zeros_like(alpha))
        one_minus = 1.0 - alpha
        trans_incl = torch.cumprod(one_minus, dim=1)  # [t, k, 256]
        trans_before = torch.cat([torch.ones_like(trans_incl[:, :1]), trans_incl[:, :-1]], dim=1)
        weights = alpha * trans_before
        feat_chunks.append(torch.einsum("tkp,tkf->tpf", weights, features[gid]).reshape(-1, num_feat))
        trans_chunks.append(trans_incl[:, -1].reshape(-1))
        pixel_chunks.append(pix_xy.reshape(-1, 2))
        start = stop

    image = torch.zeros(height * width, num_feat, device=device, dtype=dtype)
    trans = torch.ones(height * width, device=device, dtype=dtype)
    if pixel_chunks:
        pix = torch.cat(pixel_chunks)
        inside = (pix[:, 0] < width) & (pix[:, 1] < height)
        linear = (pix[:, 1] * width + pix[:, 0])[inside]
        image = image.index_put((linear,), torch.cat(feat_chunks)[inside])
        trans = trans.index_put((linear,), torch.cat(trans_chunks)[inside])
    return image.reshape(height, width, num_feat), trans.reshape(height, width)

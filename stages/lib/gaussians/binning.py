"""Tile binning: which depth-sorted Gaussians touch each 16x16 tile (shared by all backends)."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from stages.lib.gaussians.projection import Projection, tile_grid

TILE_SIZE = 16


@dataclass
class TileBins:
    """Per-tile lists of Gaussian indices, each sorted front to back (row-major tile order)."""

    offsets: torch.Tensor  # [num_tiles + 1] int32; tile t owns gauss_ids[offsets[t]:offsets[t+1]]
    gauss_ids: torch.Tensor  # [P] int32 Gaussian indices
    tiles_x: int
    tiles_y: int


def bin_gaussians(proj: Projection, width: int, height: int) -> TileBins:
    """Assign every visible Gaussian to the tiles its alpha >= 1/255 footprint touches.

    A Gaussian reaches pixel column u when |u + 0.5 - x| <= extent_x (likewise rows); the pair
    list is sorted by tile, and by camera depth within a tile (stable sort of a depth order).
    """
    tiles_x, tiles_y = tile_grid(width, height, TILE_SIZE)
    device = proj.means2d.device
    with torch.no_grad():
        visible = torch.nonzero(proj.radii > 0).squeeze(-1)
        order = visible[torch.argsort(proj.depths.detach()[visible])]  # front to back
        m2 = proj.means2d.detach()[order].float()
        ext = proj.extents[order].float() + 1e-3  # margin: the kernels test alpha exactly
        lo = torch.ceil(m2 - ext - 0.5)
        hi = torch.floor(m2 + ext - 0.5)
        size = torch.tensor([width - 1, height - 1], device=device, dtype=lo.dtype)
        lo = torch.clamp(lo, min=0).minimum(size).long() // TILE_SIZE  # [M, 2] first tile (x, y)
        hi = torch.clamp(hi, min=0).minimum(size).long() // TILE_SIZE  # [M, 2] last tile
        span = hi - lo + 1  # [M, 2]
        counts = span[:, 0] * span[:, 1]  # [M]
        pair_gauss = torch.repeat_interleave(torch.arange(order.numel(), device=device), counts)
        first_pair = torch.cumsum(counts, 0) - counts
        local = torch.arange(pair_gauss.numel(), device=device) - first_pair[pair_gauss]
        span_x = span[pair_gauss, 0]
        tile_x = lo[pair_gauss, 0] + local % span_x
        tile_y = lo[pair_gauss, 1] + local // span_x
        tile_ids = tile_y * tiles_x + tile_x
        tile_ids, perm = torch.sort(tile_ids, stable=True)
        gauss_ids = order[pair_gauss[perm]].to(torch.int32)
        per_tile = torch.bincount(tile_ids, minlength=tiles_x * tiles_y)
        offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.int64, device=device)
        offsets[1:] = torch.cumsum(per_tile, 0)
    return TileBins(offsets=offsets.to(torch.int32), gauss_ids=gauss_ids, tiles_x=tiles_x,
                    tiles_y=tiles_y)

"""An instance mask as the one polygon a YOLO segmentation label holds, and that polygon back as a mask.

A YOLO label line holds one polygon per instance, but a mask may have holes and several components (an
object cut in two by a nearer one). Every boundary of the mask (outer boundaries and holes, OpenCV's
two-level contours) becomes a loop of boundary-pixel centres; the loops are joined into one polygon by
zero-width bridges (the components along a minimum spanning tree of their closest vertex pairs, each hole to
the nearest vertex of its own boundary): the polygon walks into each bridge, around the loop behind it and
back along the same bridge. Ultralytics' own COCO converter joins components the same way (its
`merge_multi_segment`, a chain in file order) but drops holes. Filled with the even-odd rule (OpenCV's
fillPoly, which Ultralytics uses), a bridge traversed twice cancels and a hole loop empties its hole; only the
pixels a bridge crosses outside the mask are filled (benchmarks/results/convert.md measures the IoU). Every
component is kept, so the polygon's extent is the mask's box.

Coordinates are pixel centres, (column + 0.5, row + 0.5), the project's pixel convention: Ultralytics
scales normalised coordinates back by the image size and truncates them to integers, which gives exactly
the boundary pixels again.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree


def mask_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1), ends exclusive, of the pixels of a [H, W] bool mask; None when it is empty."""
    rows, columns = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return None
    return int(columns[0]), int(rows[0]), int(columns[-1]) + 1, int(rows[-1]) + 1


def mask_loops(mask: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """The boundary loops of a [H, W] bool mask, each [P, 2] int (x, y) pixels, every boundary pixel in
    order, and the outer loop each belongs to [L] (its own index for an outer loop, the enclosing one for a hole)."""
    box = mask_box(mask)
    if box is None:
        return [], np.zeros(0, np.int64)
    x0, y0, x1, y1 = box
    crop = np.ascontiguousarray(mask[y0:y1, x0:x1], dtype=np.uint8)
    contours, hierarchy = cv2.findContours(crop, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE, offset=(x0, y0))
    parents = hierarchy[0, :, 3]
    return ([contour[:, 0, :].astype(np.int64) for contour in contours],
            np.where(parents < 0, np.arange(len(contours)), parents))


def grow_tree(loops: list[np.ndarray], members: list[int], root: int) -> list[tuple[int, int, int, int]]:
    """Prim's minimum spanning tree over the closest vertex pairs of the loops `members` (indices into loops
    [P_i, 2]), grown from `root`: the bridges (parent loop, its vertex, child loop, its vertex) in the order the
    loops join.

    Every vertex keeps its distance to the tree and where on the tree that is, updated by one KD-tree query
    of all vertices against each loop that joins."""
    points = np.concatenate([loops[k] for k in members])  # [V, 2]
    starts = np.cumsum([0] + [len(loops[k]) for k in members])  # [M + 1] each member's first vertex
    distance = np.full(len(points), np.inf)  # [V] to the tree
    link = np.zeros((len(points), 2), np.int64)  # [V] (tree loop, its vertex) at that distance
    waiting = np.ones(len(members), bool)  # members not yet in the tree
    bridges, newest = [], members.index(root)
    waiting[newest] = False
    owner = np.repeat(np.arange(len(members)), np.diff(starts))  # [V] member of each vertex
    while waiting.any():
        open_points = np.flatnonzero(waiting[owner])
        found, nearest = cKDTree(loops[members[newest]]).query(points[open_points])
        closer = found < distance[open_points]
        distance[open_points[closer]] = found[closer]
        link[open_points[closer]] = np.stack([np.full(closer.sum(), members[newest]), nearest[closer]], axis=1)
        per_member = np.where(waiting, np.minimum.reduceat(distance, starts[:-1]), np.inf)  # [M]
        newest = int(np.argmin(per_member))
        vertex = starts[newest] + int(np.argmin(distance[starts[newest]:starts[newest + 1]]))
        waiting[newest] = False
        bridges.append((int(link[vertex, 0]), int(link[vertex, 1]), members[newest], int(vertex - starts[newest])))
    return bridges


def corner_loops(loops: list[np.ndarray], anchors: list[list[int]]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each loop [P_i, 2] cut down to the vertices where its direction turns and its `anchors` (bridge ends),
    at least one; and for each loop the new place [P_i] of every old vertex (meaningful for the kept ones)."""
    starts = np.cumsum([0] + [len(loop) for loop in loops])  # [L + 1]
    points = np.concatenate(loops)  # [V, 2]
    following, preceding = np.arange(1, len(points) + 1), np.arange(-1, len(points) - 1)
    following[starts[1:] - 1], preceding[starts[:-1]] = starts[:-1], starts[1:] - 1  # around each loop
    step = points[following] - points  # [V, 2] to the next vertex of the loop
    kept = np.any(step != step[preceding], axis=1)
    kept[[starts[k] + vertex for k, vertices in enumerate(anchors) for vertex in vertices]] = True
    kept[starts[:-1][~np.logical_or.reduceat(kept, starts[:-1])]] = True  # a straight loop keeps its first vertex
    new_place = np.cumsum(kept) - 1  # [V]
    kept_starts = np.cumsum([0] + list(np.add.reduceat(kept, starts[:-1])))  # [L + 1]
    return (np.split(points[kept], kept_starts[1:-1]),
            [new_place[starts[k]:starts[k + 1]] - kept_starts[k] for k in range(len(loops))])


def hole_bridges(loops: list[np.ndarray], outer: np.ndarray) -> list[tuple[int, int, int, int]]:
    """A bridge (outer loop, its vertex, hole, its vertex) from each hole to the nearest vertex of its own outer
    boundary: nothing lies between the two but the component (and, rarely, another of its holes)."""
    bridges = []
    for boundary in np.unique(outer):
        holes = [int(k) for k in np.flatnonzero(outer == boundary) if k != boundary]
        if holes:
            starts = np.cumsum([0] + [len(loops[hole]) for hole in holes])
            distances, nearest = cKDTree(loops[boundary]).query(np.concatenate([loops[hole] for hole in holes]))
            for k, hole in enumerate(holes):
                own = int(np.argmin(distances[starts[k]:starts[k + 1]]))
                bridges.append((int(boundary), int(nearest[starts[k] + own]), hole, own))
    return bridges


def joined_polygon(loops: list[np.ndarray], outer: np.ndarray, root: int) -> np.ndarray:
    """The loops [P_i, 2] (outer boundaries and holes, `outer` [L] as mask_loops gives it) joined into one
    closed polygon [P, 2] by zero-width bridges (module docstring): the components along their minimum
    spanning tree from the outer loop `root`, each hole to its own boundary; straight runs are left out.

    A loop's tour starts at its entry vertex (where its bridge from the parent lands), goes once around, and
    at each vertex where a child's bridge leaves, takes the child's tour and comes back to that vertex; a
    child's tour ends at its entry again. Tours are built children first (they join after their parents)."""
    components = [int(k) for k in np.unique(outer)]
    bridges = grow_tree(loops, components, root) + hole_bridges(loops, outer)
    anchors: list[list[int]] = [[] for _ in loops]
    for parent, parent_vertex, child, child_vertex in bridges:
        anchors[parent].append(parent_vertex)
        anchors[child].append(child_vertex)
    loops, place = corner_loops(loops, anchors)
    entry = {root: 0}
    leaving: list[list[tuple[int, int]]] = [[] for _ in loops]  # per loop: (its vertex, child)
    for parent, parent_vertex, child, child_vertex in bridges:
        entry[child] = int(place[child][child_vertex])
        leaving[parent].append((int(place[parent][parent_vertex]), child))
    tours: dict[int, np.ndarray] = {}
    for loop in [child for _, _, child, _ in reversed(bridges)] + [root]:
        size, start = len(loops[loop]), entry[loop]
        ring = np.roll(loops[loop], -start, axis=0)  # [P, 2] from the entry around
        pieces, done = [], 0
        for step, child in sorted(((vertex - start) % size, child) for vertex, child in leaving[loop]):
            pieces += [ring[done:step + 1], tours.pop(child), ring[step:step + 1]]
            done = step + 1
        pieces.append(ring[done:])
        if loop != root:
            pieces.append(ring[:1])  # back at the entry, to return along the bridge
        tours[loop] = np.concatenate(pieces)
    return tours[root]


@dataclass
class MaskPolygon:
    """A mask as one YOLO polygon."""

    points: np.ndarray  # [P, 2] float (x, y) pixel-centre coordinates, P >= 3
    loops: int  # boundaries it joins (outer boundaries and holes)


def mask_polygon(mask: np.ndarray) -> MaskPolygon:
    """The YOLO polygon of a non-empty [H, W] bool mask, every component and hole joined (a polygon of fewer
    than three points repeats its last one; YOLO needs three)."""
    loops, outer = mask_loops(mask)
    if not loops:
        raise ValueError("empty mask: no polygon")
    polygon = joined_polygon(loops, outer, int(outer[0])) if len(loops) > 1 else corner_loops(loops, [[]])[0][0]
    if len(polygon) < 3:
        polygon = np.concatenate([polygon, np.repeat(polygon[-1:], 3 - len(polygon), axis=0)])
    return MaskPolygon(polygon + 0.5, len(loops))


def polygon_mask(polygon: np.ndarray, width: int, height: int) -> np.ndarray:
    """A polygon [P, 2] in pixel coordinates filled the way Ultralytics rasterises its labels (truncated to
    integer pixels, OpenCV's fillPoly): a [height, width] bool mask."""
    mask = np.zeros((height, width), np.uint8)
    cv2.fillPoly(mask, [np.asarray(polygon, dtype=np.float64).astype(np.int32)], 1)
    return mask.astype(bool)


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two [H, W] bool masks (1 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0

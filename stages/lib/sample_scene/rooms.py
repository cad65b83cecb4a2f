"""Furnished rooms: floor, walls, ceiling, windows, pictures, shelves with books, cabinets, sofas,
tables, chairs, rugs and clutter, each with procedural textures, plus the lighting set-ups.

A room spans x in [-half_x, half_x], y in [-half_y, half_y], z in [0, height]; the floor is z = 0.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import textures as tx
from .meshes import Mesh, box, revolve
from .raytrace import Light, Lighting

WALL_T = 0.1
FLOOR_KINDS = ("planks", "tiles", "carpet")


@dataclass
class Room:
    """A room's meshes and what placement code needs to know about them.

    obstacles: AABBs [2, 3] (min, max) of furniture and clutter; tables: free table tops as
    [xmin, xmax, ymin, ymax, z_top]; windows: window centres [3] on the walls.
    """

    meshes: list[Mesh]
    half_x: float
    half_y: float
    height: float
    obstacles: list[np.ndarray] = field(default_factory=list)
    tables: list[np.ndarray] = field(default_factory=list)
    windows: list[np.ndarray] = field(default_factory=list)

    def add(self, meshes: list[Mesh], aabb: np.ndarray | None = None) -> None:
        """Add meshes and (optionally) their AABB as an obstacle."""
        self.meshes.extend(meshes)
        if aabb is not None:
            self.obstacles.append(np.asarray(aabb, np.float64))

    def free(self, aabb: np.ndarray, margin: float = 0.05) -> bool:
        """Whether `aabb` [2, 3] stays inside the walls and clear of all obstacles by `margin` horizontally
        (vertically, touching is allowed: things stand on tables)."""
        lo, hi = aabb
        if lo[0] < -self.half_x + margin or hi[0] > self.half_x - margin:
            return False
        if lo[1] < -self.half_y + margin or hi[1] > self.half_y - margin:
            return False
        gap = np.array([margin, margin, 0.0])
        return all(np.any(lo >= o[1] + gap) or np.any(hi <= o[0] - gap) for o in self.obstacles)


def _aabb(center, size) -> np.ndarray:
    """AABB [2, 3] of a box."""
    c, h = np.asarray(center, float), np.asarray(size, float) / 2
    return np.stack([c - h, c + h])


def _textured_box(center, size, texture, tile_m=0.5, **material) -> tuple[list[Mesh], np.ndarray]:
    """One box mesh and its AABB."""
    return [box(center, size, texture, tile_m, **material)], _aabb(center, size)


def _table(rng, xy, size_xy, top_z, wood) -> tuple[list[Mesh], np.ndarray, np.ndarray]:
    """A table: top board (support) and four legs. Returns meshes, AABB, free top [xmin, xmax, ymin, ymax, z]."""
    thick = 0.035
    sx, sy = size_xy
    meshes = [box([xy[0], xy[1], top_z - thick / 2], [sx, sy, thick], wood, 0.8, support=True, specular=0.12, shininess=25)]
    leg = rng.uniform(0.04, 0.06)
    for dx in (-1, 1):
        for dy in (-1, 1):
            cx, cy = xy[0] + dx * (sx / 2 - leg), xy[1] + dy * (sy / 2 - leg)
            meshes.append(box([cx, cy, (top_z - thick) / 2], [leg, leg, top_z - thick], wood, 0.8, specular=0.1))
    top = np.array([xy[0] - sx / 2, xy[0] + sx / 2, xy[1] - sy / 2, xy[1] + sy / 2, top_z])
    return meshes, _aabb([xy[0], xy[1], top_z / 2], [sx, sy, top_z]), top


def _chair(rng, xy, facing: float, wood, cloth) -> tuple[list[Mesh], np.ndarray]:
    """A chair facing `facing` radians; the back is on the opposite side."""
    seat, size = rng.uniform(0.42, 0.48), rng.uniform(0.4, 0.48)
    meshes = [box([xy[0], xy[1], seat], [size, size, 0.05], cloth, 0.4)]
    for dx in (-1, 1):
        for dy in (-1, 1):
            meshes.append(box([xy[0] + dx * (size / 2 - 0.03), xy[1] + dy * (size / 2 - 0.03), seat / 2],
                              [0.035, 0.035, seat], wood, 0.8))
    back = np.array([-np.cos(facing), -np.sin(facing)]) * (size / 2 - 0.02)
    back_size = [0.04, size, 0.45] if abs(np.cos(facing)) > 0.5 else [size, 0.04, 0.45]
    meshes.append(box([xy[0] + back[0], xy[1] + back[1], seat + 0.25], back_size, wood, 0.8))
    return meshes, _aabb([xy[0], xy[1], (seat + 0.5) / 2], [size, size, seat + 0.5])


def clutter_item(rng: np.random.Generator, xy, z: float, max_size: float = 0.25) -> tuple[list[Mesh], np.ndarray]:
    """A random small item standing at (xy, z): a book stack, a cup, a box or a ball."""
    kind = rng.choice(["books", "cup", "box", "ball"])
    s = rng.uniform(0.4, 1.0) * max_size
    if kind == "books":
        meshes, z0 = [], z
        for _ in range(int(rng.integers(1, 4))):
            h = rng.uniform(0.02, 0.05)
            meshes.append(box([xy[0], xy[1], z0 + h / 2], [s, 0.75 * s, h], tx.book_spines(rng, 64), 0.3, specular=0.1))
            z0 += h
        return meshes, _aabb([xy[0], xy[1], (z + z0) / 2], [s, 0.75 * s, z0 - z])
    if kind == "cup":
        r, h = 0.3 * s, 0.7 * s
        cup = revolve([0, r * 0.8, r, r * 0.9, 0], [0, 0, h, h, h * 0.3], tx.solid(tx.random_colour(rng)), specular=0.4, shininess=40)
        return [cup.transformed(np.eye(3), [xy[0], xy[1], z])], _aabb([xy[0], xy[1], z + h / 2], [2 * r, 2 * r, h])
    if kind == "box":
        size = [s, rng.uniform(0.5, 1.0) * s, rng.uniform(0.3, 0.8) * s]
        return _textured_box([xy[0], xy[1], z + size[2] / 2], size, tx.product_label(rng, 128, 64), s, specular=0.15)
    r = 0.4 * s
    angles = np.linspace(-np.pi / 2, np.pi / 2, 12)
    ball = revolve(r * np.cos(angles), r + r * np.sin(angles), tx.fabric(rng, 64), specular=0.3, shininess=30)
    return [ball.transformed(np.eye(3), [xy[0], xy[1], z])], _aabb([xy[0], xy[1], z + r], [2 * r, 2 * r, 2 * r])


def _along_wall(room: Room, rng, width: float, depth: float) -> tuple[np.ndarray, bool]:
    """A random footprint centre against a random wall; returns (xy, along_x)."""
    wall = int(rng.integers(4))
    along_x = wall < 2
    span = (room.half_x if along_x else room.half_y) - width / 2 - 0.05
    t = rng.uniform(-span, span) if span > 0 else 0.0
    sign = -1 if wall % 2 == 0 else 1
    off = sign * ((room.half_y if along_x else room.half_x) - depth / 2 - 0.01)
    return (np.array([t, off]) if along_x else np.array([off, t])), along_x


def _shelf(room: Room, rng, wood) -> bool:
    """A bookshelf against a wall with books and items on its boards (boards are support)."""
    width, depth, height = rng.uniform(0.6, 1.2), rng.uniform(0.28, 0.4), rng.uniform(1.1, 2.0)
    xy, along_x = _along_wall(room, rng, width, depth)
    size = np.array([width, depth, height]) if along_x else np.array([depth, width, height])
    aabb = _aabb([xy[0], xy[1], height / 2], size)
    if not room.free(aabb):
        return False
    t = 0.025
    meshes = []
    side_axis = 0 if along_x else 1
    for sgn in (-1, 1):
        c = np.array([xy[0], xy[1], height / 2])
        c[side_axis] += sgn * (size[side_axis] / 2 - t / 2)
        s = size.copy()
        s[side_axis] = t
        meshes.append(box(c, s, wood, 0.8, specular=0.1))
    levels = np.linspace(0.05, height - t / 2, int(rng.integers(3, 6)))
    for z in levels:
        s = size.copy()
        s[2] = t
        meshes.append(box([xy[0], xy[1], z], s, wood, 0.8, support=True, specular=0.1))
    for z0, z1 in zip(levels[:-1], levels[1:]):
        gap = z1 - z0 - t
        run = rng.uniform(0.3, 0.9) * (width - 2 * t)
        book_size = np.array([run, depth * 0.85, gap * rng.uniform(0.6, 0.9)])
        if not along_x:
            book_size = book_size[[1, 0, 2]]
        shift = np.zeros(3)
        shift[side_axis] = rng.uniform(-1, 1) * (width - 2 * t - run) / 2
        meshes.append(box([xy[0] + shift[0], xy[1] + shift[1], z0 + t / 2 + book_size[2] / 2], book_size,
                          tx.book_spines(rng), tile_m=max(run, 0.2), specular=0.08))
    room.add(meshes, aabb)
    return True


def _cabinet(room: Room, rng, wood) -> bool:
    """A sideboard against a wall (its top is support) with an item or two on top."""
    width, depth, height = rng.uniform(0.7, 1.6), rng.uniform(0.4, 0.55), rng.uniform(0.7, 1.0)
    xy, along_x = _along_wall(room, rng, width, depth)
    size = np.array([width, depth, height]) if along_x else np.array([depth, width, height])
    aabb = _aabb([xy[0], xy[1], height / 2], size)
    if not room.free(aabb):
        return False
    body = tx.plaster(rng, 128) if rng.uniform() < 0.5 else wood
    room.add([box([xy[0], xy[1], height / 2], size, body, 0.6, support=True, specular=0.15, shininess=30)], aabb)
    for _ in range(int(rng.integers(0, 3))):
        offset = (rng.uniform(-0.35, 0.35, 2) * size[:2])
        room.add(clutter_item(rng, xy + offset, height, 0.2)[0])
    return True


def _sofa(room: Room, rng) -> bool:
    """A sofa against a wall: base, back rest and arm rests in fabric."""
    width, depth = rng.uniform(1.4, 2.2), rng.uniform(0.8, 0.95)
    xy, along_x = _along_wall(room, rng, width, depth)
    size = np.array([width, depth, 0.85]) if along_x else np.array([depth, width, 0.85])
    aabb = _aabb([xy[0], xy[1], 0.425], size)
    if not room.free(aabb):
        return False
    cloth = tx.fabric(rng)
    depth_axis = 1 if along_x else 0
    towards_wall = -np.sign(xy[depth_axis])
    meshes = [box([xy[0], xy[1], 0.22], [size[0], size[1], 0.44], cloth, 0.5, specular=0.02)]
    back_c = np.array([xy[0], xy[1], 0.62])
    back_c[depth_axis] -= towards_wall * (size[depth_axis] / 2 - 0.1)
    back_s = size.copy()
    back_s[depth_axis], back_s[2] = 0.2, 0.46
    meshes.append(box(back_c, back_s, cloth, 0.5, specular=0.02))
    side_axis = 1 - depth_axis
    for sgn in (-1, 1):
        c = np.array([xy[0], xy[1], 0.55])
        c[side_axis] += sgn * (size[side_axis] / 2 - 0.1)
        s = size.copy()
        s[side_axis], s[2] = 0.2, 0.22
        meshes.append(box(c, s, cloth, 0.5, specular=0.02))
    room.add(meshes, aabb)
    return True


def _wall_decor(room: Room, rng) -> None:
    """Pictures, a window (recorded for window light) and a door on the walls, plus skirting boards."""
    skirting = tx.solid(tx.random_colour(rng, (0.0, 0.2), (0.7, 0.95)))
    hx, hy = room.half_x, room.half_y
    room.add([box([0, -hy + 0.01, 0.04], [2 * hx, 0.02, 0.08], skirting), box([0, hy - 0.01, 0.04], [2 * hx, 0.02, 0.08], skirting),
              box([-hx + 0.01, 0, 0.04], [0.02, 2 * hy, 0.08], skirting), box([hx - 0.01, 0, 0.04], [0.02, 2 * hy, 0.08], skirting)])
    items = ["window", "door"] + ["picture"] * int(rng.integers(2, 5))
    for item in items:
        wall = int(rng.integers(4))
        along_x = wall < 2
        half = hx if along_x else hy
        sign = -1 if wall % 2 == 0 else 1
        if item == "window":
            w, h, z, tex = rng.uniform(0.9, 1.5), rng.uniform(1.0, 1.4), rng.uniform(1.3, 1.6), tx.plaster(rng, 64, [0.92, 0.96, 1.0])
        elif item == "door":
            w, h, z, tex = 0.9, 2.05, 1.025, tx.wood(rng, 128)
        else:
            w, h, z, tex = rng.uniform(0.3, 0.9), rng.uniform(0.3, 0.7), rng.uniform(1.2, 1.8), tx.painting(rng)
        t = rng.uniform(-(half - w / 2 - 0.1), half - w / 2 - 0.1)
        off = sign * ((hy if along_x else hx) - 0.015)
        centre = [t, off, z] if along_x else [off, t, z]
        size = [w, 0.03, h] if along_x else [0.03, w, h]
        room.add([box(centre, size, tex, tile_m=max(w, h) if item != "window" else 1.0, specular=0.05)])
        if item == "window":
            room.windows.append(np.array(centre) - np.array([0, sign * 0.4, 0] if along_x else [sign * 0.4, 0, 0]))


def make_room(rng: np.random.Generator, keep_out: float = 0.0, centre_table: bool = False,
              clutter: int = 6) -> Room:
    """A random furnished room.

    keep_out: half-size (m) of a square around the origin kept free of furniture (a capture orbit);
    centre_table: put a table at the origin (inside the keep-out square).
    clutter: how many loose items to scatter on free floor and table tops.
    """
    half_x = max(rng.uniform(2.0, 3.5), keep_out + 0.8)
    half_y = max(rng.uniform(1.8, 3.0), keep_out + 0.8)
    height = rng.uniform(2.5, 3.0)
    room = Room([], half_x, half_y, height)
    floor_kind = rng.choice(FLOOR_KINDS)
    floor_tex = {"planks": lambda: tx.wood(rng, 256, planks=6), "tiles": lambda: tx.tiles(rng),
                 "carpet": lambda: tx.fabric(rng)}[floor_kind]()
    floor_tile = {"planks": 1.2, "tiles": rng.uniform(0.6, 1.2), "carpet": 0.8}[floor_kind]
    wall_tex = tx.plaster(rng) if rng.uniform() < 0.6 else tx.wallpaper(rng)
    room.add([box([0, 0, -WALL_T / 2], [2 * half_x + 0.4, 2 * half_y + 0.4, WALL_T], floor_tex, floor_tile, support=True,
                  specular=0.15 if floor_kind != "carpet" else 0.0, shininess=30),
              box([0, 0, height + WALL_T / 2], [2 * half_x + 0.4, 2 * half_y + 0.4, WALL_T], tx.plaster(rng, 128), 2.0)])
    for sign in (-1, 1):
        room.add([box([sign * (half_x + WALL_T / 2), 0, height / 2], [WALL_T, 2 * half_y + 0.4, height], wall_tex, 1.5, specular=0.02),
                  box([0, sign * (half_y + WALL_T / 2), height / 2], [2 * half_x + 0.4, WALL_T, height], wall_tex, 1.5, specular=0.02)])
    _wall_decor(room, rng)
    wood = tx.wood(rng)
    if keep_out > 0:
        room.obstacles.append(np.array([[-keep_out, -keep_out, 0.0], [keep_out, keep_out, height]]))
    if centre_table:
        size = (rng.uniform(1.0, 1.4), rng.uniform(0.7, 0.9))
        meshes, _, top = _table(rng, (0.0, 0.0), size, rng.uniform(0.72, 0.78), wood)
        room.add(meshes)
        room.tables.append(top)
    if rng.uniform() < 0.6:
        rug = _aabb([rng.uniform(-0.5, 0.5) * half_x, rng.uniform(-0.5, 0.5) * half_y, 0.004], [rng.uniform(1.2, 2.4), rng.uniform(0.8, 1.8), 0.008])
        room.add([box((rug[0] + rug[1]) / 2, rug[1] - rug[0], tx.fabric(rng), 0.7, support=True, specular=0.0)])
    builders = [_shelf, _cabinet, _sofa, _shelf, _cabinet]
    for k in range(int(rng.integers(3, 6))):
        for _ in range(10):
            build = builders[k % len(builders)]
            if (build(room, rng) if build is _sofa else build(room, rng, wood)):
                break
    for _ in range(int(rng.integers(1, 3))):
        _free_table(room, rng, wood)
    _scatter_clutter(room, rng, clutter)
    return room


def _free_table(room: Room, rng, wood) -> None:
    """A dining or coffee table somewhere free, with a chair or two when tall."""
    for _ in range(20):
        size = (rng.uniform(0.7, 1.6), rng.uniform(0.5, 0.9))
        top_z = rng.choice([rng.uniform(0.4, 0.5), rng.uniform(0.72, 0.78)])
        xy = (rng.uniform(-room.half_x + 0.6, room.half_x - 0.6), rng.uniform(-room.half_y + 0.6, room.half_y - 0.6))
        meshes, aabb, top = _table(rng, xy, size, top_z, wood)
        if room.free(aabb, 0.3):
            room.add(meshes, aabb)
            room.tables.append(top)
            if top_z > 0.6:
                cloth = tx.fabric(rng, 64)
                for sgn in (-1, 1):
                    cxy = (xy[0] + sgn * (size[0] / 2 + 0.3), xy[1])
                    chair_meshes, chair_box = _chair(rng, cxy, 0.0 if sgn < 0 else np.pi, wood, cloth)
                    if room.free(chair_box, 0.02):
                        room.add(chair_meshes, chair_box)
            return


def _scatter_clutter(room: Room, rng, count: int) -> None:
    """Loose items on the floor and on table tops (obstacles, so placement avoids them)."""
    for _ in range(count):
        for _ in range(10):
            if room.tables and rng.uniform() < 0.5:
                top = room.tables[int(rng.integers(len(room.tables)))]
                xy, z = np.array([rng.uniform(top[0] + 0.1, top[1] - 0.1), rng.uniform(top[2] + 0.1, top[3] - 0.1)]), top[4]
            else:
                xy, z = np.array([rng.uniform(-room.half_x, room.half_x), rng.uniform(-room.half_y, room.half_y)]), 0.0
            meshes, aabb = clutter_item(rng, xy, z)
            if room.free(aabb, 0.03):
                room.add(meshes, aabb)
                break


def capture_lighting(room: Room, rng: np.random.Generator) -> Lighting:
    """Soft, neutral light of an object capture: two ceiling lamps and strong ambient."""
    lights = []
    for _ in range(2):
        pos = np.array([rng.uniform(-0.6, 0.6) * room.half_x, rng.uniform(-0.6, 0.6) * room.half_y, room.height - 0.3])
        lights.append(Light(pos, np.array([1.0, 0.98, 0.95]) * rng.uniform(2.5, 3.5)))
    return Lighting(lights, np.array([0.22, 0.22, 0.23]))


def scene_lighting(room: Room, rng: np.random.Generator) -> Lighting:
    """Lighting of the photos (backgrounds and tests): a warm lamp, window light and dimmer ambient."""
    lamp = np.array([rng.uniform(-0.8, 0.8) * room.half_x, rng.uniform(-0.8, 0.8) * room.half_y, rng.uniform(1.4, room.height - 0.3)])
    lights = [Light(lamp, np.array([1.0, 0.78, 0.52]) * rng.uniform(2.0, 4.0))]
    if room.windows:
        window = room.windows[int(rng.integers(len(room.windows)))]
        lights.append(Light(window, np.array([0.75, 0.85, 1.0]) * rng.uniform(1.5, 3.5)))
    ambient = np.array([0.08, 0.08, 0.09]) * rng.uniform(0.7, 1.4)
    return Lighting(lights, ambient)


def flash(lighting: Lighting, eye: np.ndarray, distance: float) -> Lighting:
    """The lighting plus an on-camera flash: a point light just above the lens, scaled to the subject distance."""
    flash_light = Light(np.asarray(eye) + np.array([0, 0, 0.05]), np.ones(3) * 1.6 * distance**2)
    return Lighting(lighting.lights + [flash_light], lighting.ambient * 0.6)

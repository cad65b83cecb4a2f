"""Where and how an object goes into a background: poses on placement planes and random poses.

A pose maps object-model coordinates into the background camera frame (OpenCV, x right, y down,
z forward): x_cam = scale * R @ x_model + t. The camera frame is the world frame for rendering
(viewmat = identity).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stages.records.planes import PlacementPlane

NEAR_DEPTH = 0.05  # objects closer than this to the camera are rejected (metres or model units)
MODEL_OPACITY = 0.5  # model points: Gaussians at least this opaque (each alone puts the pixel under its mean in the
#                      mask at compose's default threshold; fainter ones, e.g. an unpruned halo, need not)


@dataclass
class ObjectFrame:
    """What extract.json says about an object model (model units, splat frame)."""

    normal: np.ndarray  # [3] unit, from the removed ground plane towards the object
    base_point: np.ndarray  # [3] on the ground plane under the object
    height: float  # object height along `normal`

    @property
    def centre(self) -> np.ndarray:
        """Mid-height point on the normal through the base point [3]."""
        return self.base_point + 0.5 * self.height * self.normal


@dataclass
class Pose:
    """A similarity transform model -> camera frame and how it was chosen."""

    rotation: np.ndarray  # [3, 3]
    translation: np.ndarray  # [3]
    scale: float
    kind: str  # "plane" or "random"

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform model points [M, 3] into the camera frame [M, 3]."""
        return self.scale * points @ self.rotation.T + self.translation


def model_points(means: np.ndarray, opacities: np.ndarray) -> np.ndarray:
    """The object's model points [M, 3]: the means [N, 3] of its Gaussians whose opacity [N] is at least
    MODEL_OPACITY (all means when none is)."""
    opaque = np.asarray(opacities).reshape(-1) >= MODEL_OPACITY
    return np.asarray(means, dtype=np.float64)[opaque if opaque.any() else slice(None)]


@dataclass
class MetricFrame:
    """The object's own frame of the poses compose exports (BOP's model frame): metres, z up along the ground
    normal, origin at the centre of the 3-D bounding box of the object's model points in these axes."""

    axes: np.ndarray  # [3, 3] columns: the frame's x, y, z axes in model coordinates (z = the ground normal)
    origin: np.ndarray  # [3] model units
    metres_per_unit: float  # the object's real height / its height in model units

    def from_model(self, points: np.ndarray) -> np.ndarray:
        """Model points [M, 3] (model units) in this frame [M, 3] (metres)."""
        return self.metres_per_unit * (np.asarray(points, dtype=np.float64) - self.origin) @ self.axes

    def as_dict(self) -> dict:
        """The frame as JSON-able lists (compose writes it into its dataset's info.object_models)."""
        return {"axes": self.axes.tolist(), "origin": self.origin.tolist(), "metres_per_unit": self.metres_per_unit}

    @classmethod
    def from_dict(cls, data: dict) -> "MetricFrame":
        """The frame of as_dict's output."""
        return cls(np.asarray(data["axes"], dtype=np.float64), np.asarray(data["origin"], dtype=np.float64),
                   float(data["metres_per_unit"]))


def metric_frame(obj: ObjectFrame, points: np.ndarray, height_m: float) -> MetricFrame:
    """The metric frame of an object of real height `height_m` whose model points [N, 3] (model units,
    model_points) stand on the ground of `obj`; its x axis is the model's direction that the smallest
    rotation taking z onto the normal takes x to."""
    axes = rotation_aligning(np.array([0.0, 0.0, 1.0]), obj.normal)
    local = (np.asarray(points, dtype=np.float64) - obj.base_point) @ axes  # [N, 3] in the frame's axes
    origin = obj.base_point + axes @ (0.5 * (local.min(axis=0) + local.max(axis=0)))
    return MetricFrame(axes, origin, float(height_m) / obj.height)


def metric_pose(pose: Pose, frame: MetricFrame) -> tuple[np.ndarray, np.ndarray, float]:
    """The rigid pose (R [3, 3], t [3] metres) of the real-size object in the camera frame that gives the
    image `pose` rendered, and the render scale k: the rendered object was k times its real size at k * t.

    x_cam = s R_p (origin + axes x / m) + t_p = k (R x + t) with k = s / m, R = R_p axes and
    t = (s R_p origin + t_p) / k; scaling the camera frame by 1 / k leaves every projection unchanged.
    k is 1 for a plane placement on metric depth, where t is also the object's place in the background's depth.
    """
    k = pose.scale / frame.metres_per_unit
    rotation = pose.rotation @ frame.axes
    translation = (pose.scale * pose.rotation @ frame.origin + pose.translation) / k
    return rotation, translation, float(k)


def rotation_about_axis(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix [3, 3] by `angle` radians about the unit `axis` [3] (Rodrigues)."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    cross = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * cross @ cross


def rotation_aligning(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The smallest rotation [3, 3] taking unit vector `source` [3] onto unit vector `target` [3]."""
    a = np.asarray(source, dtype=np.float64) / np.linalg.norm(source)
    b = np.asarray(target, dtype=np.float64) / np.linalg.norm(target)
    axis = np.cross(a, b)
    sin_angle, cos_angle = np.linalg.norm(axis), float(np.dot(a, b))
    if sin_angle < 1e-9:
        if cos_angle > 0:
            return np.eye(3)
        helper = np.eye(3)[int(np.argmin(np.abs(a)))]  # any axis perpendicular to a works for 180 deg
        return rotation_about_axis(np.cross(a, helper), math.pi)
    return rotation_about_axis(axis, math.atan2(sin_angle, cos_angle))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed rotation [3, 3] (normalised Gaussian quaternion)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def pose_on_plane(obj: ObjectFrame, point: np.ndarray, plane_normal: np.ndarray, yaw: float,
                  scale: float) -> Pose:
    """Stand the object on a plane point: its normal onto the plane normal, turned by `yaw` about it.

    point, plane_normal: [3] camera frame. The base point lands exactly on `point`.
    """
    align = rotation_aligning(obj.normal, plane_normal)
    rotation = rotation_about_axis(plane_normal, yaw) @ align
    translation = np.asarray(point, dtype=np.float64) - scale * rotation @ obj.base_point
    return Pose(rotation, translation, float(scale), "plane")


def scale_for_apparent_height(obj: ObjectFrame, depth: float, focal_y: float, image_height: int,
                              fraction: float) -> float:
    """Model->camera scale that makes the object `fraction` of the image height tall at `depth`."""
    return fraction * image_height * depth / (focal_y * obj.height)


def sample_plane_point(planes: list[PlacementPlane], rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A plane drawn with probability proportional to its area, then one of its points uniformly.

    Returns (point [3], normal [3]) in the camera frame.
    """
    areas = np.array([max(p.area, 0.0) for p in planes], dtype=np.float64)
    weights = areas / areas.sum() if areas.sum() > 0 else np.full(len(planes), 1.0 / len(planes))
    plane = planes[int(rng.choice(len(planes), p=weights))]
    return plane.points[int(rng.integers(len(plane.points)))], plane.normal


def sample_plane_pose(obj: ObjectFrame, height_m: float, planes: list[PlacementPlane], metric: bool,
                      K: np.ndarray, image_height: int, rng: np.random.Generator,
                      apparent_height_range: tuple[float, float]) -> Pose:
    """Stand the object at a random point of a random plane with a random turn about the up axis.

    Metric planes: scale = height_m / model height, so nearer objects come out larger. Relative
    (non-metric) planes cannot give a real size: the object gets a random apparent height instead.
    """
    point, normal = sample_plane_point(planes, rng)
    yaw = rng.uniform(0.0, 2.0 * math.pi)
    if metric:
        scale = height_m / obj.height
    else:
        fraction = rng.uniform(*apparent_height_range)
        scale = scale_for_apparent_height(obj, float(point[2]), float(K[1, 1]), image_height, fraction)
    return pose_on_plane(obj, point, normal, yaw, scale)


def footprint_radius(obj: ObjectFrame, points: np.ndarray) -> float:
    """How far the model points [M, 3] reach from the object's up axis (the normal through its base point), in
    model units: the radius of the circle its footprint and overhang (a plant's leaves) stand in."""
    offsets = np.asarray(points, dtype=np.float64) - obj.base_point
    across = offsets - np.outer(offsets @ obj.normal, obj.normal)
    return float(np.linalg.norm(across, axis=1).max(initial=0.0))


def plane_under(planes: list[PlacementPlane], point: np.ndarray) -> PlacementPlane:
    """The plane among `planes` with a placement point nearest to `point` [3] (the plane an object stands on)."""
    return min(planes, key=lambda plane: float(np.min(np.linalg.norm(plane.points - point, axis=1))))


def sample_pose_beside(obj: ObjectFrame, height_m: float, radius: float, plane: PlacementPlane,
                       anchor: np.ndarray, anchor_radius: float, spread: float, metric: bool, K: np.ndarray,
                       image_height: int, rng: np.random.Generator,
                       apparent_height_range: tuple[float, float]) -> Pose | None:
    """Stand the object on `plane` beside another one standing at `anchor` [3] (camera frame): at a placement point
    whose distance from it is the sum of both objects' footprint radii (`radius`: this one's in model units;
    `anchor_radius`: the other's in the plane's units) times a uniform factor in [1, 1 + spread], so that they do
    not intersect and often overlap in the image. Scales as sample_plane_pose does (a non-metric plane draws an
    apparent height, applied at the chosen point's depth). None when no placement point lies at such a distance.
    """
    yaw = rng.uniform(0.0, 2.0 * math.pi)
    fraction = None if metric else rng.uniform(*apparent_height_range)

    def scale_at(depth: float) -> float:
        if fraction is None:
            return height_m / obj.height
        return scale_for_apparent_height(obj, depth, float(K[1, 1]), image_height, fraction)

    reach = anchor_radius + scale_at(float(anchor[2])) * radius
    distance = np.linalg.norm(plane.points - anchor, axis=1)
    candidates = np.flatnonzero((distance >= reach) & (distance <= reach * (1.0 + spread)))
    if candidates.size == 0:
        return None
    point = plane.points[int(rng.choice(candidates))]
    return pose_on_plane(obj, point, plane.normal, yaw, scale_at(float(point[2])))


def sample_random_pose(obj: ObjectFrame, K: np.ndarray, width: int, height: int, rng: np.random.Generator,
                       apparent_height_range: tuple[float, float],
                       depth_range: tuple[float, float] = (2.0, 4.0)) -> Pose:
    """Random viewpoint (any rotation, including in-plane), random 2-D position and apparent size.

    The object's centre goes to a uniform pixel at a random depth (the depth only orders objects
    among themselves; random placements get no background depth test).
    """
    rotation = random_rotation(rng)
    u, v = rng.uniform(0.0, width), rng.uniform(0.0, height)
    depth = rng.uniform(*depth_range)
    scale = scale_for_apparent_height(obj, depth, float(K[1, 1]), height, rng.uniform(*apparent_height_range))
    centre = depth * np.linalg.solve(K, np.array([u, v, 1.0]))
    translation = centre - scale * rotation @ obj.centre
    return Pose(rotation, translation, float(scale), "random")

"""Scenes of box primitives: ``primitives.json`` ⇄ :class:`Box` ⇄ MJCF (``scene.xml``).

``primitives.json`` is a list of ``{"center": [3], "rotation": [3x3 row-major],
"half_size": [3], "source": "planar" | "contact"}`` (an optional ``"name"`` is kept).
``scene.xml`` holds the same boxes as static geoms of the world body and loads on its own.

Collision bits: scene geoms have ``contype=1, conaffinity=2`` and the humanoid's
``contype=2, conaffinity=1``, so the humanoid collides with the scene, while neither the
scene's boxes (all static) nor the humanoid's own segments collide among themselves.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from crisp_gym.atomic import write_text

SOURCES = ("planar", "contact")
SCENE_CONTYPE = 1
SCENE_CONAFFINITY = 2


@dataclass(frozen=True)
class Box:
    """An oriented box primitive.

    Attributes:
        center: (3,) world position of the box centre (metres).
        rotation: (3, 3) rotation matrix whose columns are the box axes in the world frame.
        half_size: (3,) positive half extents along the box axes.
        source: ``"planar"`` (fitted to observed points) or ``"contact"`` (from human contact).
        name: optional geom name.
    """

    center: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    half_size: np.ndarray = field(default_factory=lambda: np.full(3, 0.5))
    source: str = "planar"
    name: str | None = None

    def __post_init__(self) -> None:
        center = np.asarray(self.center, dtype=float).reshape(-1)
        rotation = np.asarray(self.rotation, dtype=float)
        half = np.asarray(self.half_size, dtype=float).reshape(-1)
        if center.shape != (3,) or half.shape != (3,):
            raise ValueError(f"center and half_size must have 3 entries, got {center.shape}, {half.shape}")
        if rotation.shape == (9,):
            rotation = rotation.reshape(3, 3)
        if rotation.shape != (3, 3):
            raise ValueError(f"rotation must be 3x3, got {rotation.shape}")
        for key, arr in (("center", center), ("rotation", rotation), ("half_size", half)):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"box {key} has non-finite values: {arr.tolist()}")
        if np.any(half <= 0):
            raise ValueError(f"half_size must be positive, got {half.tolist()}")
        if np.abs(rotation @ rotation.T - np.eye(3)).max() > 1e-5 or np.linalg.det(rotation) < 0:
            raise ValueError("rotation must be a proper rotation matrix (orthonormal, det +1)")
        if self.source not in SOURCES:
            raise ValueError(f"source must be one of {SOURCES}, got {self.source!r}")
        object.__setattr__(self, "center", center)
        object.__setattr__(self, "rotation", rotation)
        object.__setattr__(self, "half_size", half)

    @property
    def quat(self) -> np.ndarray:
        """Orientation as a w x y z quaternion."""
        q = np.empty(4)
        mujoco.mju_mat2Quat(q, self.rotation.reshape(-1))
        return q

    def corners(self) -> np.ndarray:
        """(8, 3) world corners."""
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
        return self.center + (signs * self.half_size) @ self.rotation.T

    def transformed(self, world_from_old: np.ndarray) -> Box:
        """The same box moved by a rigid (4, 4) transform."""
        m = np.asarray(world_from_old, dtype=float)
        if m.shape != (4, 4):
            raise ValueError(f"world_from_old must be (4, 4), got {m.shape}")
        return Box(center=m[:3, :3] @ self.center + m[:3, 3], rotation=m[:3, :3] @ self.rotation,
                   half_size=self.half_size, source=self.source, name=self.name)

    def translated(self, offset: np.ndarray) -> Box:
        """The same box shifted by ``offset`` (3,)."""
        return Box(center=self.center + np.asarray(offset, dtype=float), rotation=self.rotation,
                   half_size=self.half_size, source=self.source, name=self.name)

    def top_height(self) -> float:
        """Highest z of the box."""
        return float(self.corners()[:, 2].max())

    def to_json(self) -> dict:
        item = {"center": self.center.tolist(), "rotation": self.rotation.reshape(-1).tolist(),
                "half_size": self.half_size.tolist(), "source": self.source}
        if self.name:
            item["name"] = self.name
        return item

    @classmethod
    def from_json(cls, item: dict) -> Box:
        missing = {"center", "rotation", "half_size"} - set(item)
        if missing:
            raise ValueError(f"primitive is missing {sorted(missing)}: {item}")
        return cls(center=item["center"], rotation=item["rotation"], half_size=item["half_size"],
                   source=item.get("source", "planar"), name=item.get("name"))


def floor_box(size: float = 40.0, thickness: float = 0.1, height: float = 0.0) -> Box:
    """A large flat box whose top face is at ``height``."""
    return Box(center=[0.0, 0.0, height - thickness / 2], half_size=[size / 2, size / 2, thickness / 2],
               name="floor")


def save_primitives(boxes: list[Box], path: str | Path) -> Path:
    """Write ``primitives.json`` atomically."""
    return write_text(path, json.dumps([b.to_json() for b in boxes], indent=1))


def load_primitives(path: str | Path) -> list[Box]:
    """Read ``primitives.json``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no primitives file at {path}")
    try:
        items = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON: {err}") from None
    if not isinstance(items, list):
        raise ValueError(f"{path} must hold a list of boxes, got {type(items).__name__}")
    return [Box.from_json(item) for item in items]


def add_boxes(spec: mujoco.MjSpec, boxes: list[Box], friction: tuple[float, float, float] = (1.0, 0.005, 0.0001),
              prefix: str = "scene_") -> None:
    """Add ``boxes`` as static geoms of ``spec``'s world body."""
    colors = {"planar": (0.45, 0.6, 0.85, 1.0), "contact": (0.9, 0.55, 0.3, 1.0)}
    for i, box in enumerate(boxes):
        spec.worldbody.add_geom(
            name=box.name if box.name else f"{prefix}{i}", type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=box.center, quat=box.quat, size=box.half_size, friction=friction,
            contype=SCENE_CONTYPE, conaffinity=SCENE_CONAFFINITY, rgba=colors[box.source])


def build_scene_spec(boxes: list[Box], friction: tuple[float, float, float] = (1.0, 0.005, 0.0001)) -> mujoco.MjSpec:
    """An MJCF model holding only ``boxes`` (plus a light), loadable on its own."""
    if not boxes:
        raise ValueError("a scene needs at least one box")
    names = [b.name for b in boxes if b.name]
    if len(names) != len(set(names)):
        raise ValueError(f"box names must be unique, got {names}")
    spec = mujoco.MjSpec()
    spec.modelname = "crisp_scene"
    spec.worldbody.add_light(name="sun", pos=(0, 0, 6), dir=(0, 0.3, -1), type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
    add_boxes(spec, boxes, friction)
    return spec


def write_scene_xml(boxes: list[Box], path: str | Path) -> Path:
    """Write ``scene.xml`` atomically."""
    return write_text(path, build_scene_spec(boxes).to_xml())


def boxes_from_model(model: mujoco.MjModel) -> list[Box]:
    """The world body's box geoms of a compiled model (e.g. a loaded ``scene.xml``)."""
    boxes = []
    for g in range(model.ngeom):
        if model.geom_bodyid[g] != 0 or model.geom_type[g] != mujoco.mjtGeom.mjGEOM_BOX:
            continue
        mat = np.empty(9)
        mujoco.mju_quat2Mat(mat, model.geom_quat[g])
        name = model.geom(g).name or None
        boxes.append(Box(center=model.geom_pos[g].copy(), rotation=mat.reshape(3, 3),
                         half_size=model.geom_size[g].copy(), name=name))
    return boxes


def load_scene_xml(path: str | Path) -> list[Box]:
    """Boxes of a ``scene.xml``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no scene file at {path}")
    return boxes_from_model(mujoco.MjModel.from_xml_path(str(path)))


def sample_surface_points(boxes: list[Box], spacing: float = 0.05,
                          rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Points on the boxes' faces, about one per ``spacing``² of area, with outward normals.

    Returns (P, 3) points and (P, 3) unit normals. With ``rng`` the points are jittered
    uniformly within their grid cell; without it they are the cell centres.
    """
    if spacing <= 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    points, normals = [], []
    for box in boxes:
        for axis in range(3):
            u, v = [a for a in range(3) if a != axis]
            nu = max(1, int(np.ceil(2 * box.half_size[u] / spacing)))
            nv = max(1, int(np.ceil(2 * box.half_size[v] / spacing)))
            gu, gv = np.meshgrid((np.arange(nu) + 0.5) / nu, (np.arange(nv) + 0.5) / nv, indexing="ij")
            gu, gv = gu.reshape(-1), gv.reshape(-1)
            if rng is not None:
                gu = gu + (rng.random(gu.shape) - 0.5) / nu
                gv = gv + (rng.random(gv.shape) - 0.5) / nv
            for sign in (-1.0, 1.0):
                local = np.zeros((gu.size, 3))
                local[:, u] = (2 * gu - 1) * box.half_size[u]
                local[:, v] = (2 * gv - 1) * box.half_size[v]
                local[:, axis] = sign * box.half_size[axis]
                points.append(box.center + local @ box.rotation.T)
                normals.append(np.broadcast_to(sign * box.rotation[:, axis], local.shape))
    return np.concatenate(points), np.concatenate(normals)

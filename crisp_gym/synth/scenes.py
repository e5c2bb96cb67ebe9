"""Box scenes of the synthetic clips: stairs, a platform and a box seat on a floor, their parameters
and the human-plausible ranges the generator draws them from."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crisp_gym.scene import Box, floor_box

# Human-plausible ranges (metres) of the randomised scene parameters; building codes put
# risers at 0.10-0.20 m and treads (goings) at 0.25-0.35 m; chairs have 0.40-0.50 m seats.
RISER_RANGE = (0.12, 0.18)
TREAD_RANGE = (0.26, 0.35)
STAIR_COUNT_RANGE = (3, 5)
STAIR_WIDTH_RANGE = (0.9, 1.4)
PLATFORM_HEIGHT_RANGE = (0.10, 0.25)
PLATFORM_LENGTH_RANGE = (0.8, 1.2)
SEAT_HEIGHT_RANGE = (0.40, 0.48)  # above ~0.48 m the 1.70 m humanoid's feet no longer reach the floor
SEAT_DEPTH_RANGE = (0.42, 0.48)
SEAT_WIDTH_RANGE = (0.40, 0.48)


@dataclass(frozen=True)
class StairsParams:
    """A straight flight along +x with solid steps standing on the floor.

    Attributes:
        riser: height of each step (m).
        tread: horizontal depth of each tread (m).
        width: width of the flight across the walking direction (m).
        count: number of risers; ``count - 1`` treads and a top landing.
        start: x of the first riser (ascending) or of the top nosing (descending), in m.
        landing: length of the top landing along x (m).
    """

    riser: float
    tread: float
    width: float
    count: int
    start: float
    landing: float

    @property
    def top(self) -> float:
        return self.riser * self.count


@dataclass(frozen=True)
class PlatformParams:
    """A raised box to step onto and off again.

    Attributes:
        height: top of the platform above the floor (m).
        length: extent along the walking direction +x (m).
        width: extent across it (m).
        start: x of the near edge (m).
    """

    height: float
    length: float
    width: float
    start: float


@dataclass(frozen=True)
class SeatParams:
    """A box seat with an optional backrest, its front edge facing +x.

    Attributes:
        height: seat top above the floor (m).
        depth: seat extent along x (m).
        width: seat extent along y (m).
        front: x of the seat's front edge (m).
        backrest_height: backrest top above the seat (m); 0 for a stool without one.
        backrest_thickness: backrest extent along x (m).
    """

    height: float
    depth: float
    width: float
    front: float
    backrest_height: float
    backrest_thickness: float = 0.05


@dataclass(frozen=True)
class Level:
    """A horizontal support surface along the path: x in [x0, x1] at height z."""

    x0: float
    x1: float
    z: float


def _block(x0: float, x1: float, width: float, top: float, name: str) -> Box:
    """A solid box standing on the floor (z = 0) spanning [x0, x1] along x."""
    return Box(center=[(x0 + x1) / 2, 0.0, top / 2], half_size=[(x1 - x0) / 2, width / 2, top / 2], name=name)


def stairs_levels(p: StairsParams, descending: bool) -> list[Level]:
    """Support levels of a flight (floor excluded), in walking order."""
    if descending:
        levels = [Level(p.start - p.landing, p.start, p.top)]
        levels += [Level(p.start + (j - 1) * p.tread, p.start + j * p.tread, (p.count - j) * p.riser)
                   for j in range(1, p.count)]
    else:
        levels = [Level(p.start + (j - 1) * p.tread, p.start + j * p.tread, j * p.riser)
                  for j in range(1, p.count)]
        end = p.start + (p.count - 1) * p.tread
        levels.append(Level(end, end + p.landing, p.top))
    return levels


def stairs_boxes(params: StairsParams, descending: bool = False) -> list[Box]:
    """Floor plus one solid block per step and the top landing.

    Ascending flights rise along +x from ``params.start``; descending ones start with the
    landing (ending at ``params.start``) and go down along +x.
    """
    _check_stairs(params)
    boxes = [floor_box()]
    for i, level in enumerate(stairs_levels(params, descending)):
        is_landing = np.isclose(level.z, params.top)
        boxes.append(_block(level.x0, level.x1, params.width, level.z, "landing" if is_landing else f"step_{i}"))
    return boxes


def platform_boxes(params: PlatformParams) -> list[Box]:
    """Floor plus the platform block."""
    if params.height <= 0 or params.length <= 0 or params.width <= 0:
        raise ValueError(f"platform dimensions must be positive, got {params}")
    return [floor_box(), _block(params.start, params.start + params.length, params.width, params.height, "platform")]


def seat_boxes(params: SeatParams) -> list[Box]:
    """Floor, the seat block and, when ``backrest_height > 0``, a backrest behind it."""
    if min(params.height, params.depth, params.width, params.backrest_thickness) <= 0:
        raise ValueError(f"seat dimensions must be positive, got {params}")
    back = params.front - params.depth
    boxes = [floor_box(), _block(back, params.front, params.width, params.height, "seat")]
    if params.backrest_height > 0:
        boxes.append(_block(back - params.backrest_thickness, back, params.width,
                            params.height + params.backrest_height, "backrest"))
    return boxes


def _check_stairs(p: StairsParams) -> None:
    if p.riser <= 0 or p.tread <= 0 or p.width <= 0 or p.landing <= 0:
        raise ValueError(f"stair dimensions must be positive, got {p}")
    if p.count < 1:
        raise ValueError(f"a flight needs at least one riser, got count={p.count}")


def sample_stairs_params(rng: np.random.Generator, descending: bool = False) -> StairsParams:
    """Random flight within :data:`RISER_RANGE`, :data:`TREAD_RANGE`, :data:`STAIR_COUNT_RANGE`."""
    start = rng.uniform(0.9, 1.3) if descending else rng.uniform(1.3, 1.8)
    return StairsParams(
        riser=round(rng.uniform(*RISER_RANGE), 3), tread=round(rng.uniform(*TREAD_RANGE), 3),
        width=round(rng.uniform(*STAIR_WIDTH_RANGE), 3),
        count=int(rng.integers(STAIR_COUNT_RANGE[0], STAIR_COUNT_RANGE[1] + 1)),
        start=round(start, 3), landing=round(start + 0.6 if descending else rng.uniform(1.2, 1.6), 3))


def sample_platform_params(rng: np.random.Generator) -> PlatformParams:
    """Random platform within :data:`PLATFORM_HEIGHT_RANGE` and :data:`PLATFORM_LENGTH_RANGE`."""
    return PlatformParams(height=round(rng.uniform(*PLATFORM_HEIGHT_RANGE), 3),
                          length=round(rng.uniform(*PLATFORM_LENGTH_RANGE), 3),
                          width=round(rng.uniform(0.9, 1.4), 3), start=round(rng.uniform(1.2, 1.8), 3))


def sample_seat_params(rng: np.random.Generator) -> SeatParams:
    """Random seat within :data:`SEAT_HEIGHT_RANGE`, :data:`SEAT_DEPTH_RANGE`, :data:`SEAT_WIDTH_RANGE`.

    The front edge is placed behind the standing person's calves (feet at x = 0).
    """
    return SeatParams(height=round(rng.uniform(*SEAT_HEIGHT_RANGE), 3),
                      depth=round(rng.uniform(*SEAT_DEPTH_RANGE), 3),
                      width=round(rng.uniform(*SEAT_WIDTH_RANGE), 3),
                      front=round(-rng.uniform(0.08, 0.12), 3),
                      backrest_height=round(rng.uniform(0.35, 0.45), 3) if rng.random() < 0.6 else 0.0)

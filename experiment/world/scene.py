"""The static world of one trial: floor, shelf unit, items, obstacles, parking pose.

``build_scene(complexity, seed)`` is deterministic: the same seed (an int or a
sequence of ints such as ``(study_seed, trial_index)``) gives the same shelf
contents, target slot and obstacles. Obstacles exist only in high complexity.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

from experiment.world import constants as K
from experiment.world.geometry import Box, box_from_bounds

COMPLEXITIES = ("low", "high")
SHELF_COLOR = (150, 110, 75)
OBSTACLE_COLOR = (200, 50, 45)
FLOOR_COLOR = (205, 205, 200)
ITEM_COLORS = ((230, 160, 30), (60, 140, 210), (90, 170, 80), (220, 90, 140),
               (240, 220, 80), (130, 90, 190), (240, 120, 60), (70, 190, 190))


@dataclass(frozen=True, eq=False)
class Item:
    """A grocery item standing in a shelf slot.

    ``center`` (3,) world position of its centre when in the slot; ``size``
    (3,) full extents (cylinders: diameter, diameter, height), metres.
    """

    slot: int
    center: np.ndarray
    size: np.ndarray
    shape: str
    color: tuple[int, int, int]

    @property
    def name(self) -> str:
        return f"/items/{self.slot}"

    @property
    def height(self) -> float:
        return float(self.size[2])

    @property
    def width(self) -> float:
        return float(self.size[0])

    def grasp_point(self) -> np.ndarray:
        """Where the TCP goes to grasp the item in its slot (3,), m."""
        return self.center + np.array([0.0, 0.0, self.height / 2 - K.GRASP_DEPTH])


@dataclass(frozen=True, eq=False)
class Scene:
    """Everything static in one trial, plus the robot's start and parking poses (x, y, yaw)."""

    complexity: str
    seed: object
    shelf: tuple[Box, ...]
    items: tuple[Item, ...]
    target_index: int
    obstacles: tuple[Box, ...]
    park: tuple[float, float, float]
    start: tuple[float, float, float]
    collision_cache: dict = field(default_factory=dict, repr=False)

    @property
    def target(self) -> Item:
        return self.items[self.target_index]

    @property
    def stamp(self) -> str:
        return scene_stamp(self.complexity, self.seed)

    @property
    def target_slot(self) -> int:
        return self.target.slot


def scene_stamp(complexity: str, seed: object) -> str:
    """A short name of the scene ``build_scene(complexity, seed)`` builds, the same wherever it is computed: a view
    that draws the scene carries it, and a page proves which scene it drew by reading it back (hex, 16 characters)."""
    return hashlib.sha256(f"{normalise_complexity(complexity)}:{seed}".encode()).hexdigest()[:16]


def normalise_complexity(complexity) -> str:
    """'low' or 'high' from a string or a ``Complexity`` enum; ValueError otherwise."""
    value = str(getattr(complexity, "value", complexity)).lower()
    if value not in COMPLEXITIES:
        raise ValueError(f"complexity must be 'low' or 'high', got {complexity!r}")
    return value


def slot_position(slot: int) -> tuple[float, float, float]:
    """World (x, y, board top z) of the centre of a slot's footprint."""
    if not 0 <= slot < K.N_SLOTS:
        raise ValueError(f"slot must be in 0..{K.N_SLOTS - 1}, got {slot}")
    tier, col = divmod(slot, len(K.SLOT_COLUMNS_Y))
    return (K.SHELF_FRONT_X + K.SLOT_TIERS_X[tier], K.SHELF_CENTER_Y + K.SLOT_COLUMNS_Y[col],
            K.SLOT_TIERS_Z[tier])


def shelf_boxes() -> tuple[Box, ...]:
    """Uprights, back panel, plinth, the two boards and the riser between them."""
    f, cy, p = K.SHELF_FRONT_X, K.SHELF_CENTER_Y, K.PANEL
    hw, d, h = K.SHELF_WIDTH / 2, K.SHELF_DEPTH, K.SHELF_HEIGHT
    up, low = K.UPPER_BOARD_TOP, K.LOWER_BOARD_TOP
    s = K.UPPER_SETBACK
    parts = [
        ("upright_0", (f, cy - hw, 0), (f + d + p, cy - hw + p, h)),
        ("upright_1", (f, cy + hw - p, 0), (f + d + p, cy + hw, h)),
        ("back", (f + d, cy - hw + p, 0), (f + d + p, cy + hw - p, h)),
        ("plinth", (f + 0.02, cy - hw + p, 0), (f + d, cy + hw - p, low - p)),
        ("board_0", (f, cy - hw + p, low - p), (f + d, cy + hw - p, low)),
        ("riser", (f + s, cy - hw + p, low), (f + s + p, cy + hw - p, up - p)),
        ("board_1", (f + s, cy - hw + p, up - p), (f + d, cy + hw - p, up)),
    ]
    return tuple(box_from_bounds(f"/shelf/{n}", lo, hi, SHELF_COLOR) for n, lo, hi in parts)


def _make_item(rng: np.random.Generator, slot: int) -> Item:
    x, y, z = slot_position(slot)
    w = float(rng.uniform(*K.ITEM_WIDTH_RANGE))
    h = float(rng.uniform(*K.ITEM_HEIGHT_RANGE))
    shape = "cylinder" if rng.random() < 0.5 else "box"
    color = ITEM_COLORS[int(rng.integers(len(ITEM_COLORS)))]
    return Item(slot, np.array([x, y, z + h / 2]), np.array([w, w, h]), shape, color)


def _make_obstacles(rng: np.random.Generator, target: Item) -> tuple[Box, ...]:
    count = int(rng.integers(K.OBSTACLE_COUNT_RANGE[0], K.OBSTACLE_COUNT_RANGE[1] + 1))
    top = float(target.center[2] + target.height / 2 + rng.uniform(*K.OBSTACLE_ABOVE_ITEM_RANGE))
    main_w = float(rng.uniform(*K.OBSTACLE_WIDTH_RANGE))
    y0 = float(target.center[1])
    specs = [(y0, main_w, top)]
    sides = [-1.0, 1.0] if count == 3 else [float(rng.choice([-1.0, 1.0]))]
    for sign in sides:
        w = float(rng.uniform(*K.OBSTACLE_WIDTH_RANGE))
        offset = (main_w + w) / 2 + float(rng.uniform(*K.OBSTACLE_SIDE_GAP_RANGE))
        specs.append((y0 + sign * offset, w, top * float(rng.uniform(*K.OBSTACLE_SIDE_HEIGHT_RANGE))))
    back = K.SHELF_FRONT_X - K.OBSTACLE_FRONT_GAP
    boxes = []
    for i, (y, w, h) in enumerate(specs):
        depth = float(rng.uniform(*K.OBSTACLE_DEPTH_RANGE))
        boxes.append(box_from_bounds(f"/obstacles/{i}", (back - depth, y - w / 2, 0.0),
                                     (back, y + w / 2, h), OBSTACLE_COLOR))
    return tuple(boxes)


def park_pose(target: Item) -> tuple[float, float, float]:
    """Base pose (x, y, yaw) with the mast axis in line with the target column."""
    mx = K.SHELF_FRONT_X - K.MAST_STANDOFF
    return (mx - K.MAST_XY[0], float(target.center[1]) - K.MAST_XY[1], 0.0)


def build_scene(complexity, seed, target_slot: int | None = None) -> Scene:
    """The scene of one trial, deterministic in ``seed`` (int or sequence of ints).

    ``target_slot`` (0..N_SLOTS-1, slot = tier * 4 + column) overrides the
    seeded choice of the target item's slot.
    """
    level = normalise_complexity(complexity)
    rng = np.random.default_rng(seed)
    drawn = int(rng.integers(K.N_SLOTS))
    slot = drawn if target_slot is None else int(target_slot)
    slot_position(slot)  # validates
    items: list[Item] = []
    target_index = 0
    for s in range(K.N_SLOTS):
        fill = rng.random() < K.ITEM_FILL_PROBABILITY
        item = _make_item(rng, s)
        if s == slot:
            target_index = len(items)
        if fill or s == slot:
            items.append(item)
    target = items[target_index]
    obstacles = _make_obstacles(rng, target) if level == "high" else ()
    park = park_pose(target)
    start = (park[0] - K.DRIVE_DISTANCE, park[1], 0.0)
    return Scene(level, seed, shelf_boxes(), tuple(items), target_index, obstacles, park, start)


def scene_boxes(scene: Scene) -> list[Box]:
    """Static geometry in world coordinates: floor, shelf, other items, obstacles.

    Names: ``/floor``, ``/shelf/<part>``, ``/items/<slot>`` (every item but the
    target, which moves: see ``link_poses``), ``/obstacles/<i>``.
    """
    (x0, y0), (x1, y1) = K.FLOOR_BOUNDS
    floor = box_from_bounds("/floor", (x0, y0, -0.02), (x1, y1, 0.0), FLOOR_COLOR)
    others = [Box(it.name, it.center.copy(), it.size.copy(), it.color, it.shape)
              for i, it in enumerate(scene.items) if i != scene.target_index]
    return [floor, *scene.shelf, *others, *scene.obstacles]


def transfer_height(scene: Scene) -> float:
    """TCP height (m) at which the carried target item clears every obstacle and the bin."""
    hang = scene.target.height - K.GRASP_DEPTH
    grasp_z = float(scene.target.grasp_point()[2])
    z = max(grasp_z + K.PREGRASP_HEIGHT, K.TRANSFER_MIN_Z, K.BIN_RIM + hang + K.CLEARANCE)
    for ob in scene.obstacles:
        z = max(z, float(ob.hi[2]) + hang + K.CLEARANCE)
    return z

"""Procedural houses: labmaze layouts with furniture and wall panels.

A house is a pure function of its seed:

1. :class:`labmaze.RandomMaze` lays out rooms joined by doors and corridors on a
   grid of ``CELL_SIZE_M`` cells, 15 x 15 by default; the seed may name a larger grid
   for long routes (:mod:`envs.house_grid`).
2. Each room gets its own wall and floor texture from one of labmaze's texture
   styles (the same textures dm_control's maze arenas use), chosen per house.
3. Furniture-like boxes and cylinders stand at labmaze's object cells, pushed
   against walls, and coloured panels hang on room walls: visual landmarks, so
   first-person frames from two rooms of a house can be told apart. Furniture
   that would cut the navigable space in two is left out.
4. Walls and furniture are rasterised into an :class:`~envs.geometry.OccupancyMap`
   (and a :class:`~envs.geodesic.GeodesicGraph` over it) on first use.

A house is a layout only: it knows nothing of MuJoCo. :mod:`envs.house_mesh` builds
the textured MuJoCo model of a layout (one mesh, one texture atlas), as dm_control's
maze arenas build theirs from a labmaze layout.

Splits ``train`` / ``val`` / ``test`` are disjoint seed ranges (default 61 / 11 /
18 houses, as in the paper) that can be enlarged up to ``MAX_HOUSES_PER_SPLIT``.
"""
from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field

import labmaze
import numpy as np
from labmaze import assets as labmaze_assets

from envs.geodesic import GeodesicGraph, count_components, navigable_beside
from envs.geometry import GEODESIC_RESOLUTION_M, OCCUPANCY_RESOLUTION_M, OccupancyMap
from envs.house_grid import DEFAULT_GRID_SIZE_CELLS, house_seed, max_rooms, split_house_seed

#: Side of a labmaze cell, metres.
CELL_SIZE_M = 1.0
#: Wall height, metres.
WALL_HEIGHT_M = 2.2
#: Camera height above the floor, metres.
EYE_HEIGHT_M = 0.9
#: Vertical field of view of the first-person camera, degrees.
FIELD_OF_VIEW_DEG = 90.0
#: Default labmaze grid size in cells (odd, as labmaze requires); see :mod:`envs.house_grid`.
MAZE_SIZE_CELLS = DEFAULT_GRID_SIZE_CELLS
#: Room sizes in cells passed to labmaze (room counts: :func:`envs.house_grid.max_rooms`).
ROOM_MIN_SIZE_CELLS = 3
ROOM_MAX_SIZE_CELLS = 5
OBJECTS_PER_ROOM = 2
#: Probability that a piece of furniture is a box (else a cylinder).
BOX_PROBABILITY = 0.6
#: Range of a box's half sizes along x and y, metres.
BOX_HALF_SIZE_RANGE_M = (0.15, 0.3)
#: Range of a cylinder's radius, metres.
CYLINDER_RADIUS_RANGE_M = (0.12, 0.25)
#: Range of a piece of furniture's height, metres.
FURNITURE_HEIGHT_RANGE_M = (0.5, 1.4)
#: Gap left between a piece of furniture pushed against a wall and the wall, metres.
FURNITURE_WALL_GAP_M = 0.02
#: Coloured wall panels per room.
PANELS_PER_ROOM = 2
#: Ranges of a panel's centre height, width and height, metres.
PANEL_CENTRE_HEIGHT_RANGE_M = (1.0, 1.5)
PANEL_WIDTH_RANGE_M = (0.4, 0.8)
PANEL_HEIGHT_RANGE_M = (0.3, 0.6)
#: Distance of a panel in front of its wall face (no z-fighting), metres.
PANEL_WALL_OFFSET_M = 0.011
#: labmaze texture styles usable for houses.
TEXTURE_STYLES = ("style_01", "style_02", "style_03", "style_04")
#: Default number of houses per split (the paper's 61 / 11 / 18 Matterport3D split).
DEFAULT_SPLIT_SIZES = {"train": 61, "val": 11, "test": 18}
#: First seed of each split; splits can grow up to this many houses without overlapping.
MAX_HOUSES_PER_SPLIT = 100_000
SPLIT_SEED_OFFSETS = {"train": 0, "val": MAX_HOUSES_PER_SPLIT, "test": 2 * MAX_HOUSES_PER_SPLIT}
#: Colours of furniture and panels (RGB in [0, 1]).
LANDMARK_PALETTE = np.array(
    [
        [0.85, 0.20, 0.20],
        [0.20, 0.60, 0.90],
        [0.95, 0.80, 0.20],
        [0.30, 0.75, 0.35],
        [0.65, 0.35, 0.80],
        [0.95, 0.55, 0.15],
        [0.45, 0.45, 0.50],
        [0.95, 0.95, 0.95],
        [0.55, 0.35, 0.20],
        [0.10, 0.50, 0.50],
    ]
)
#: labmaze entity-layer character of a wall cell (also the room label of walls here).
WALL_CHAR = "*"
#: labmaze variations-layer label of corridor cells.
CORRIDOR_LABEL = "."
#: labmaze entity-layer character of an object cell (where furniture may stand).
OBJECT_CHAR = "G"


def split_seeds(split: str, num_houses: int | None = None, grid_size_cells: int | None = None) -> list[int]:
    """The house seeds of a split.

    Args:
        split: one of ``"train"``, ``"val"``, ``"test"``.
        num_houses: number of houses (default: 61 / 11 / 18); may be enlarged.
        grid_size_cells: the houses' labmaze grid, cells (``None``: the default 15;
            see :func:`envs.house_grid.house_seed`).

    Examples:
        >>> split_seeds("val")[:3], split_seeds("val", grid_size_cells=51)[:1]
        ([100000, 100001, 100002], [510100000])
    """
    if split not in SPLIT_SEED_OFFSETS:
        raise ValueError(f"split must be one of {sorted(SPLIT_SEED_OFFSETS)}, got {split!r}.")
    if num_houses is None:
        num_houses = DEFAULT_SPLIT_SIZES[split]
    if not isinstance(num_houses, (int, np.integer)) or not 0 < num_houses <= MAX_HOUSES_PER_SPLIT:
        raise ValueError(f"num_houses must be an int in [1, {MAX_HOUSES_PER_SPLIT}], got {num_houses!r}.")
    offset = SPLIT_SEED_OFFSETS[split]
    return [house_seed(seed, grid_size_cells) for seed in range(offset, offset + int(num_houses))]


@dataclass
class Furniture:
    """A static obstacle: ``kind`` "box" (half sizes) or "cylinder" (radius), metres."""

    kind: str
    centre_xy: np.ndarray
    half_size_m: np.ndarray
    height_m: float
    rgb: np.ndarray


@dataclass
class Panel:
    """A coloured rectangle hung on a wall face (non-blocking landmark)."""

    centre_xyz: np.ndarray
    normal_xy: np.ndarray
    width_m: float
    height_m: float
    rgb: np.ndarray


@dataclass
class House:
    """One procedural house: layout, landmarks, MuJoCo model and free-space maps.

    Build it with :func:`build_house`; the model and maps are created on first use.
    ``paint`` maps a room label to new (wall hue, floor hue) in [0, 1): the room is
    repainted (:func:`with_paint`; empty in a built house). :func:`with_furniture` gives
    the same house with other furniture.
    """

    seed: int
    entity_layer: np.ndarray
    room_labels: np.ndarray
    style: str
    wall_texture_of_label: dict[str, str]
    floor_texture_of_label: dict[str, str]
    furniture: list[Furniture]
    panels: list[Panel]
    paint: dict[str, tuple[float, float]] = field(default_factory=dict)
    cell_size_m: float = CELL_SIZE_M
    wall_height_m: float = WALL_HEIGHT_M
    eye_height_m: float = EYE_HEIGHT_M
    _occupancy: OccupancyMap | None = field(default=None, repr=False)
    _graph: GeodesicGraph | None = field(default=None, repr=False)

    @property
    def size_m(self) -> tuple[float, float]:
        """(width along x, depth along y) of the house, metres."""
        rows, cols = self.entity_layer.shape
        return cols * self.cell_size_m, rows * self.cell_size_m

    @property
    def walls(self) -> np.ndarray:
        """Boolean ``(rows, cols)`` labmaze grid, True at wall cells; row 0 at y = 0."""
        return self.entity_layer == WALL_CHAR

    @property
    def occupancy(self) -> OccupancyMap:
        """Walls and furniture rasterised at ``OCCUPANCY_RESOLUTION_M`` (built on first access)."""
        if self._occupancy is None:
            self._occupancy = OccupancyMap(_rasterise(self, self.furniture), OCCUPANCY_RESOLUTION_M)
        return self._occupancy

    @property
    def graph(self) -> GeodesicGraph:
        """Geodesic graph of the navigable space at ``GEODESIC_RESOLUTION_M`` (built on first access)."""
        if self._graph is None:
            self._graph = GeodesicGraph(self.occupancy, GEODESIC_RESOLUTION_M)
        return self._graph

    @property
    def spawn_xy(self) -> np.ndarray:
        """A deterministic navigable position (centre of the first navigable node)."""
        return self.graph.node_xy(int(np.flatnonzero(self.graph.navigable.ravel())[0]))

    def room_at(self, xy: np.ndarray) -> str:
        """Label of the room at a position (``"."`` for corridors)."""
        col = int(np.clip(xy[0] // self.cell_size_m, 0, self.entity_layer.shape[1] - 1))
        row = int(np.clip(xy[1] // self.cell_size_m, 0, self.entity_layer.shape[0] - 1))
        return str(self.room_labels[row, col])


@functools.lru_cache(maxsize=256)
def build_house(seed: int) -> House:
    """Generate the house of a seed (cached per process).

    Args:
        seed: a house seed: any non-negative int below ``GRID_SEED_STRIDE`` for a house
            of the default grid, or :func:`envs.house_grid.house_seed` of a larger one;
            :func:`split_seeds` gives the seeds of a split.

    Examples:
        >>> build_house(0).size_m, build_house(house_seed(0, 25)).size_m
        ((15.0, 15.0), (25.0, 25.0))
    """
    _, grid = split_house_seed(seed)  # validates the seed and its grid
    seed = int(seed)
    maze = labmaze.RandomMaze(
        height=grid,
        width=grid,
        max_rooms=max_rooms(grid),
        room_min_size=ROOM_MIN_SIZE_CELLS,
        room_max_size=ROOM_MAX_SIZE_CELLS,
        spawns_per_room=0,
        objects_per_room=OBJECTS_PER_ROOM,
        random_seed=seed,
    )
    # labmaze row 0 is the top of the printed map; flip so row 0 is y = 0.
    entity = np.array([list(line) for line in str(maze.entity_layer).strip("\n").split("\n")])[::-1]
    labels = np.array([list(line) for line in str(maze.variations_layer).strip("\n").split("\n")])[::-1]
    labels = np.where(entity == WALL_CHAR, WALL_CHAR, labels)
    rng = np.random.default_rng([seed, 7])
    style = TEXTURE_STYLES[int(rng.integers(len(TEXTURE_STYLES)))]
    wall_names = sorted(labmaze_assets.get_wall_texture_paths(style))
    floor_names = sorted(labmaze_assets.get_floor_texture_paths(style))
    room_names = sorted({str(x) for x in np.unique(labels)} - {WALL_CHAR})
    wall_order = rng.permutation(len(wall_names))
    floor_order = rng.permutation(len(floor_names))
    wall_texture = {name: wall_names[wall_order[i % len(wall_names)]] for i, name in enumerate(room_names)}
    floor_texture = {name: floor_names[floor_order[i % len(floor_names)]] for i, name in enumerate(room_names)}
    house = House(
        seed=seed,
        entity_layer=entity,
        room_labels=labels,
        style=style,
        wall_texture_of_label=wall_texture,
        floor_texture_of_label=floor_texture,
        furniture=[],
        panels=[],
    )
    house.furniture = _place_furniture(house, np.argwhere(entity == OBJECT_CHAR), rng)
    house.panels = _place_panels(house, rng)
    return house


def with_paint(house: House, paint: dict[str, tuple[float, float]]) -> House:
    """``house`` with rooms repainted: ``paint`` maps room labels to (wall hue, floor hue) in [0, 1).

    A layout like any other (its model is compiled by :func:`envs.house_mesh.house_model`);
    walls, furniture and the free-space maps are the house's own.

    Examples:
        >>> painted = with_paint(build_house(0), {"A": (0.0, 0.5)})
        >>> painted.paint, painted.furniture is build_house(0).furniture
        ({'A': (0.0, 0.5)}, True)
    """
    labels = {str(x) for x in np.unique(house.room_labels)} - {WALL_CHAR}
    for label, hues in paint.items():
        if label not in labels or len(hues) != 2 or not all(0.0 <= float(h) < 1.0 for h in hues):
            raise ValueError(f"paint must map room labels ({sorted(labels)}) to two hues in [0, 1), got {label!r}: {hues!r}.")
    return dataclasses.replace(house, paint={str(k): (float(v[0]), float(v[1])) for k, v in paint.items()}, _occupancy=house._occupancy, _graph=house._graph)


def with_furniture(house: House, furniture: list[Furniture]) -> House:
    """``house`` with ``furniture`` instead of its own: its occupancy and geodesic graph are
    those of the new pieces (built on first use). Walls, textures and panels stay.

    Examples:
        >>> house = build_house(0)
        >>> bare = with_furniture(house, [])
        >>> bool(bare.occupancy.occupied.sum() < house.occupancy.occupied.sum())
        True
    """
    return dataclasses.replace(house, furniture=list(furniture), _occupancy=None, _graph=None)


def furniture_footprint(house: House, piece: Furniture) -> np.ndarray:
    """Boolean occupancy grid (``OCCUPANCY_RESOLUTION_M``, row 0 at y = 0) of one piece in ``house``."""
    return _footprint(piece, *_cell_centres(house))


def random_furniture(rng: np.random.Generator, centre_xy: np.ndarray) -> Furniture:
    """A piece of furniture drawn as :func:`build_house` draws them (kind, size, height, colour) at ``centre_xy``."""
    kind = "box" if rng.random() < BOX_PROBABILITY else "cylinder"
    half = rng.uniform(*BOX_HALF_SIZE_RANGE_M, size=2) if kind == "box" else np.full(2, rng.uniform(*CYLINDER_RADIUS_RANGE_M))
    return Furniture(
        kind=kind,
        centre_xy=np.asarray(centre_xy, dtype=np.float64),
        half_size_m=half,
        height_m=float(rng.uniform(*FURNITURE_HEIGHT_RANGE_M)),
        rgb=LANDMARK_PALETTE[int(rng.integers(len(LANDMARK_PALETTE)))],
    )


def _place_furniture(house: House, cells: np.ndarray, rng: np.random.Generator) -> list[Furniture]:
    """Furniture at labmaze object cells, pushed towards a neighbouring wall.

    A piece is kept only if the navigable space stays in one piece with it (as many
    8-connected components of navigable nodes as the walls alone leave). The
    navigable nodes are updated piece by piece with
    :func:`~envs.geodesic.navigable_beside`: exactly the nodes of
    ``GeodesicGraph(OccupancyMap(_rasterise(house, kept + [piece])))``, without a
    distance transform of the whole house per piece.
    """
    kept: list[Furniture] = []
    size = house.cell_size_m
    navigable = GeodesicGraph(OccupancyMap(_rasterise(house, []), OCCUPANCY_RESOLUTION_M)).navigable
    base_components = count_components(navigable)
    xs, ys = _cell_centres(house)
    for row, col in cells:
        kind = "box" if rng.random() < BOX_PROBABILITY else "cylinder"
        if kind == "box":
            half = rng.uniform(*BOX_HALF_SIZE_RANGE_M, size=2)
        else:
            half = np.full(2, rng.uniform(*CYLINDER_RADIUS_RANGE_M))
        centre = np.array([(col + 0.5) * size, (row + 0.5) * size])
        wall_dirs = [
            np.array(d)
            for d in ((1, 0), (-1, 0), (0, 1), (0, -1))
            if house.walls[row + d[1], col + d[0]]
        ]
        if wall_dirs:
            push = wall_dirs[int(rng.integers(len(wall_dirs)))]
            centre = centre + push * (0.5 * size - np.abs(push) @ half - FURNITURE_WALL_GAP_M)
        piece = Furniture(
            kind=kind,
            centre_xy=centre,
            half_size_m=half,
            height_m=float(rng.uniform(*FURNITURE_HEIGHT_RANGE_M)),
            rgb=LANDMARK_PALETTE[int(rng.integers(len(LANDMARK_PALETTE)))],
        )
        trial = navigable & navigable_beside(_footprint(piece, xs, ys), OCCUPANCY_RESOLUTION_M, GEODESIC_RESOLUTION_M)
        if count_components(trial) <= base_components:
            kept.append(piece)
            navigable = trial
    return kept


def _place_panels(house: House, rng: np.random.Generator) -> list[Panel]:
    """Coloured panels on wall faces that border room cells."""
    panels: list[Panel] = []
    faces = wall_faces(house)
    by_label: dict[str, list] = {}
    for face in faces:
        if face[3] != CORRIDOR_LABEL:
            by_label.setdefault(face[3], []).append(face)
    for label in sorted(by_label):
        candidates = by_label[label]
        for index in rng.choice(len(candidates), size=min(PANELS_PER_ROOM, len(candidates)), replace=False):
            start, end, normal, _ = candidates[int(index)]
            centre = 0.5 * (start + end) + normal * PANEL_WALL_OFFSET_M
            panels.append(
                Panel(
                    centre_xyz=np.array([centre[0], centre[1], rng.uniform(*PANEL_CENTRE_HEIGHT_RANGE_M)]),
                    normal_xy=normal,
                    width_m=float(rng.uniform(*PANEL_WIDTH_RANGE_M)),
                    height_m=float(rng.uniform(*PANEL_HEIGHT_RANGE_M)),
                    rgb=LANDMARK_PALETTE[int(rng.integers(len(LANDMARK_PALETTE)))],
                )
            )
    return panels


def _rasterise(house: House, furniture: list[Furniture]) -> np.ndarray:
    """Occupancy grid (row 0 at y = 0) of walls and furniture at ``OCCUPANCY_RESOLUTION_M``."""
    factor = int(round(house.cell_size_m / OCCUPANCY_RESOLUTION_M))
    occupied = np.kron(house.walls, np.ones((factor, factor), dtype=bool))
    xs, ys = _cell_centres(house)
    for piece in furniture:
        occupied |= _footprint(piece, xs, ys)
    return occupied


def _cell_centres(house: House) -> tuple[np.ndarray, np.ndarray]:
    """x of every occupancy-grid column and y of every row (cell centres), metres."""
    factor = int(round(house.cell_size_m / OCCUPANCY_RESOLUTION_M))
    rows, cols = house.walls.shape[0] * factor, house.walls.shape[1] * factor
    return (np.arange(cols) + 0.5) * OCCUPANCY_RESOLUTION_M, (np.arange(rows) + 0.5) * OCCUPANCY_RESOLUTION_M


def _footprint(piece: Furniture, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Boolean occupancy grid of one piece of furniture alone (cells whose centre it covers)."""
    dx = xs[None, :] - piece.centre_xy[0]
    dy = ys[:, None] - piece.centre_xy[1]
    if piece.kind == "box":
        return (np.abs(dx) <= piece.half_size_m[0]) & (np.abs(dy) <= piece.half_size_m[1])
    return dx**2 + dy**2 <= piece.half_size_m[0] ** 2


def wall_faces(house: House) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, str]]:
    """Wall faces bordering free cells, collinear neighbours with one label merged.

    Returns:
        (start_xy, end_xy, normal_xy pointing into free space, label of the free cell).
    """
    walls = house.walls
    rows, cols = walls.shape
    size = house.cell_size_m
    faces = []
    # normal direction (dx, dy) -> for each wall cell, the free neighbour at (row+dy, col+dx)
    for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        runs: dict[tuple, list] = {}
        for row in range(rows):
            for col in range(cols):
                nr, nc = row + dy, col + dx
                if not walls[row, col] or not (0 <= nr < rows and 0 <= nc < cols) or walls[nr, nc]:
                    continue
                label = str(house.room_labels[nr, nc])
                # the face lies on the shared edge; runs go along the edge direction
                if dx:
                    line, along = (col + (dx > 0)), row  # vertical edge x = line
                else:
                    line, along = (row + (dy > 0)), col  # horizontal edge y = line
                runs.setdefault((line, label), []).append(along)
        for (line, label), positions in runs.items():
            positions.sort()
            start = positions[0]
            for i, pos in enumerate(positions):
                last = i == len(positions) - 1
                if last or positions[i + 1] != pos + 1:
                    a, b = start * size, (pos + 1) * size
                    if dx:
                        p0, p1 = np.array([line * size, a]), np.array([line * size, b])
                    else:
                        p0, p1 = np.array([a, line * size]), np.array([b, line * size])
                    faces.append((p0, p1, np.array([dx, dy], dtype=float), label))
                    if not last:
                        start = positions[i + 1]
    return faces

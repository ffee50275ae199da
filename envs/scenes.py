"""Procedural houses: labmaze layouts built into lean, textured MuJoCo models.

A house is a pure function of its seed:

1. :class:`labmaze.RandomMaze` lays out rooms joined by doors and corridors on a
   grid of ``CELL_SIZE_M`` cells.
2. Wall faces that border free space become quads, collinear runs merged, grouped
   by the room (or corridor) they face; each group is ONE textured mesh, so a
   house is drawn with a handful of geoms (fast on a CPU renderer).
3. Each room gets its own wall and floor texture from one of labmaze's texture
   styles (the same textures dm_control's maze arenas use), chosen per house.
4. Furniture-like boxes and cylinders stand at labmaze's object cells, pushed
   against walls, and coloured panels hang on room walls: visual landmarks, so
   first-person frames from two rooms of a house can be told apart. Furniture
   that would cut the navigable space in two is left out.

Splits ``train`` / ``val`` / ``test`` are disjoint seed ranges (default 61 / 11 /
18 houses, as in the paper) that can be enlarged up to ``MAX_HOUSES_PER_SPLIT``.
"""
from __future__ import annotations

import functools
import io
from dataclasses import dataclass, field

import labmaze
import numpy as np
from labmaze import assets as labmaze_assets

from envs.geometry import GEODESIC_RESOLUTION_M, OCCUPANCY_RESOLUTION_M, GeodesicGraph, OccupancyMap

#: Side of a labmaze cell, metres.
CELL_SIZE_M = 1.0
#: Wall height, metres.
WALL_HEIGHT_M = 2.2
#: Camera height above the floor, metres.
EYE_HEIGHT_M = 0.9
#: Vertical field of view of the first-person camera, degrees.
FIELD_OF_VIEW_DEG = 90.0
#: labmaze grid size in cells (odd, as labmaze requires).
MAZE_SIZE_CELLS = 15
#: Room counts and sizes in cells passed to labmaze.
MAX_ROOMS = 6
ROOM_MIN_SIZE_CELLS = 3
ROOM_MAX_SIZE_CELLS = 5
OBJECTS_PER_ROOM = 2
#: Side of a texture once downscaled for the GPU-less renderer, pixels.
TEXTURE_SIZE_PX = 128
#: Texture repeat: metres of wall or floor covered by one texture tile.
TEXTURE_TILE_M = 1.0
#: Sides of the prism drawn for a cylindrical piece of furniture.
CYLINDER_SIDES = 8
#: Width of one colour stripe in the landmark palette texture, pixels.
PALETTE_STRIPE_PX = 16
#: Coloured wall panels per room.
PANELS_PER_ROOM = 2
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

WALL_CHAR = "*"
CORRIDOR_LABEL = "."


def split_seeds(split: str, num_houses: int | None = None) -> list[int]:
    """The house seeds of a split.

    Args:
        split: one of ``"train"``, ``"val"``, ``"test"``.
        num_houses: number of houses (default: 61 / 11 / 18); may be enlarged.

    Examples:
        >>> split_seeds("val")[:3]
        [100000, 100001, 100002]
    """
    if split not in SPLIT_SEED_OFFSETS:
        raise ValueError(f"split must be one of {sorted(SPLIT_SEED_OFFSETS)}, got {split!r}.")
    if num_houses is None:
        num_houses = DEFAULT_SPLIT_SIZES[split]
    if not isinstance(num_houses, (int, np.integer)) or not 0 < num_houses <= MAX_HOUSES_PER_SPLIT:
        raise ValueError(f"num_houses must be an int in [1, {MAX_HOUSES_PER_SPLIT}], got {num_houses!r}.")
    offset = SPLIT_SEED_OFFSETS[split]
    return list(range(offset, offset + int(num_houses)))


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
    """

    seed: int
    entity_layer: np.ndarray
    room_labels: np.ndarray
    style: str
    wall_texture_of_label: dict[str, str]
    floor_texture_of_label: dict[str, str]
    furniture: list[Furniture]
    panels: list[Panel]
    cell_size_m: float = CELL_SIZE_M
    wall_height_m: float = WALL_HEIGHT_M
    eye_height_m: float = EYE_HEIGHT_M
    _model: object = field(default=None, repr=False)
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
        if self._occupancy is None:
            self._occupancy = OccupancyMap(_rasterise(self, self.furniture), OCCUPANCY_RESOLUTION_M)
        return self._occupancy

    @property
    def graph(self) -> GeodesicGraph:
        if self._graph is None:
            self._graph = GeodesicGraph(self.occupancy, GEODESIC_RESOLUTION_M)
        return self._graph

    @property
    def model(self):
        """The compiled :class:`mujoco.MjModel` (built on first access)."""
        if self._model is None:
            import mujoco

            xml, assets = house_mjcf(self)
            self._model = mujoco.MjModel.from_xml_string(xml, assets)
        return self._model

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
        seed: any non-negative int; :func:`split_seeds` gives the seeds of a split.

    Examples:
        >>> house = build_house(0)
        >>> house.size_m
        (15.0, 15.0)
    """
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}.")
    seed = int(seed)
    maze = labmaze.RandomMaze(
        height=MAZE_SIZE_CELLS,
        width=MAZE_SIZE_CELLS,
        max_rooms=MAX_ROOMS,
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
    house.furniture = _place_furniture(house, np.argwhere(entity == "G"), rng)
    house.panels = _place_panels(house, rng)
    return house


def _place_furniture(house: House, cells: np.ndarray, rng: np.random.Generator) -> list[Furniture]:
    """Furniture at labmaze object cells, pushed towards a neighbouring wall.

    A piece is kept only if the navigable space stays in one piece with it.
    """
    kept: list[Furniture] = []
    size = house.cell_size_m
    base_components = GeodesicGraph(OccupancyMap(_rasterise(house, []), OCCUPANCY_RESOLUTION_M)).components()
    for row, col in cells:
        kind = "box" if rng.random() < 0.6 else "cylinder"
        if kind == "box":
            half = rng.uniform(0.15, 0.3, size=2)
        else:
            half = np.full(2, rng.uniform(0.12, 0.25))
        centre = np.array([(col + 0.5) * size, (row + 0.5) * size])
        wall_dirs = [
            np.array(d)
            for d in ((1, 0), (-1, 0), (0, 1), (0, -1))
            if house.walls[row + d[1], col + d[0]]
        ]
        if wall_dirs:
            push = wall_dirs[int(rng.integers(len(wall_dirs)))]
            centre = centre + push * (0.5 * size - np.abs(push) @ half - 0.02)
        piece = Furniture(
            kind=kind,
            centre_xy=centre,
            half_size_m=half,
            height_m=float(rng.uniform(0.5, 1.4)),
            rgb=LANDMARK_PALETTE[int(rng.integers(len(LANDMARK_PALETTE)))],
        )
        trial = OccupancyMap(_rasterise(house, kept + [piece]), OCCUPANCY_RESOLUTION_M)
        if GeodesicGraph(trial).components() <= base_components:
            kept.append(piece)
    return kept


def _place_panels(house: House, rng: np.random.Generator) -> list[Panel]:
    """Coloured panels on wall faces that border room cells."""
    panels: list[Panel] = []
    faces = _wall_faces(house)
    by_label: dict[str, list] = {}
    for face in faces:
        if face[3] != CORRIDOR_LABEL:
            by_label.setdefault(face[3], []).append(face)
    for label in sorted(by_label):
        candidates = by_label[label]
        for index in rng.choice(len(candidates), size=min(PANELS_PER_ROOM, len(candidates)), replace=False):
            start, end, normal, _ = candidates[int(index)]
            centre = 0.5 * (start + end) + normal * 0.011
            panels.append(
                Panel(
                    centre_xyz=np.array([centre[0], centre[1], rng.uniform(1.0, 1.5)]),
                    normal_xy=normal,
                    width_m=float(rng.uniform(0.4, 0.8)),
                    height_m=float(rng.uniform(0.3, 0.6)),
                    rgb=LANDMARK_PALETTE[int(rng.integers(len(LANDMARK_PALETTE)))],
                )
            )
    return panels


def _rasterise(house: House, furniture: list[Furniture]) -> np.ndarray:
    """Occupancy grid (row 0 at y = 0) of walls and furniture at ``OCCUPANCY_RESOLUTION_M``."""
    factor = int(round(house.cell_size_m / OCCUPANCY_RESOLUTION_M))
    occupied = np.kron(house.walls, np.ones((factor, factor), dtype=bool))
    rows, cols = occupied.shape
    ys = (np.arange(rows) + 0.5) * OCCUPANCY_RESOLUTION_M
    xs = (np.arange(cols) + 0.5) * OCCUPANCY_RESOLUTION_M
    for piece in furniture:
        dx = xs[None, :] - piece.centre_xy[0]
        dy = ys[:, None] - piece.centre_xy[1]
        if piece.kind == "box":
            occupied |= (np.abs(dx) <= piece.half_size_m[0]) & (np.abs(dy) <= piece.half_size_m[1])
        else:
            occupied |= dx**2 + dy**2 <= piece.half_size_m[0] ** 2
    return occupied


def _wall_faces(house: House) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, str]]:
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


def _polygon_mesh(polygons: list[np.ndarray]) -> tuple[str, str, str]:
    """MJCF ``vertex``/``face``/``texcoord`` strings for convex polygons.

    Each polygon is a ``(k, 5)`` array of xyz + uv rows, counter-clockwise seen
    from its front side, and is split into a triangle fan.
    """
    vertices, faces, texcoords = [], [], []
    base = 0
    for polygon in polygons:
        vertices.append(polygon[:, :3])
        texcoords.append(polygon[:, 3:])
        for i in range(1, len(polygon) - 1):
            faces.append([base, base + i, base + i + 1])
        base += len(polygon)
    fmt = lambda a: " ".join(f"{v:.4f}" for v in np.concatenate(a).ravel())  # noqa: E731
    return fmt(vertices), " ".join(str(v) for v in np.concatenate(faces)), fmt(texcoords)


def _prism_polygons(outline_xy: np.ndarray, height_m: float, uv: tuple[float, float]) -> list[np.ndarray]:
    """Side quads and top cap of a vertical prism over a counter-clockwise outline."""
    polygons = []
    u, v = uv
    count = len(outline_xy)
    for i in range(count):
        a, b = outline_xy[i], outline_xy[(i + 1) % count]
        polygons.append(np.array([[a[0], a[1], 0, u, v], [b[0], b[1], 0, u, v], [b[0], b[1], height_m, u, v], [a[0], a[1], height_m, u, v]]))
    polygons.append(np.array([[x, y, height_m, u, v] for x, y in outline_xy]))
    return polygons


def _landmark_polygons(house: House) -> list[np.ndarray]:
    """Furniture as prisms and panels as single quads, coloured through a palette texture."""
    polygons: list[np.ndarray] = []
    for piece in house.furniture:
        uv = (_palette_u(piece.rgb), 0.5)
        if piece.kind == "box":
            hx, hy = piece.half_size_m
            corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        else:
            angles = np.linspace(0, 2 * np.pi, CYLINDER_SIDES, endpoint=False)
            corners = piece.half_size_m[0] * np.stack([np.cos(angles), np.sin(angles)], axis=1)
        polygons += _prism_polygons(piece.centre_xy + corners, piece.height_m, uv)
    for panel in house.panels:
        u = _palette_u(panel.rgb)
        normal = panel.normal_xy
        tangent = np.array([-normal[1], normal[0]]) * panel.width_m / 2  # left of the normal: CCW from the front
        x, y, z = panel.centre_xyz
        centre = np.array([x, y])
        half_h = panel.height_m / 2
        a, b = centre + tangent, centre - tangent
        polygons.append(
            np.array([[b[0], b[1], z - half_h, u, 0.5], [a[0], a[1], z - half_h, u, 0.5], [a[0], a[1], z + half_h, u, 0.5], [b[0], b[1], z + half_h, u, 0.5]])
        )
    return polygons


def _palette_u(rgb: np.ndarray) -> float:
    index = int(np.argmin(np.abs(LANDMARK_PALETTE - rgb).sum(axis=1)))
    return (index + 0.5) / len(LANDMARK_PALETTE)


@functools.lru_cache(maxsize=1)
def _palette_png() -> bytes:
    """Palette texture: one vertical stripe of ``PALETTE_STRIPE_PX`` pixels per landmark colour."""
    from PIL import Image

    stripes = np.repeat((LANDMARK_PALETTE * 255).astype(np.uint8), PALETTE_STRIPE_PX, axis=0)
    image = np.repeat(stripes[None], PALETTE_STRIPE_PX, axis=0)
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    return buffer.getvalue()


def _wall_quads(house: House) -> dict[str, list[np.ndarray]]:
    quads: dict[str, list[np.ndarray]] = {}
    height = house.wall_height_m
    for p0, p1, normal, label in _wall_faces(house):
        # order the bottom edge so that (edge x up) points along the normal (front face)
        edge = p1 - p0
        if edge[0] * normal[1] - edge[1] * normal[0] > 0:  # cross(edge, z) . normal must be < 0
            p0, p1 = p1, p0
        length = float(np.hypot(*(p1 - p0)))
        u = length / TEXTURE_TILE_M
        v = height / TEXTURE_TILE_M
        quad = np.array(
            [
                [p0[0], p0[1], 0.0, 0.0, v],
                [p1[0], p1[1], 0.0, u, v],
                [p1[0], p1[1], height, u, 0.0],
                [p0[0], p0[1], height, 0.0, 0.0],
            ]
        )
        quads.setdefault(label, []).append(quad)
    return quads


def _floor_quads(house: House) -> dict[str, list[np.ndarray]]:
    quads: dict[str, list[np.ndarray]] = {}
    size = house.cell_size_m
    for row, col in np.argwhere(~house.walls):
        label = str(house.room_labels[row, col])
        x0, y0, x1, y1 = col * size, row * size, (col + 1) * size, (row + 1) * size
        t = TEXTURE_TILE_M
        quad = np.array(
            [[x0, y0, 0, x0 / t, y0 / t], [x1, y0, 0, x1 / t, y0 / t], [x1, y1, 0, x1 / t, y1 / t], [x0, y1, 0, x0 / t, y1 / t]]
        )
        quads.setdefault(label, []).append(quad)
    return quads


@functools.lru_cache(maxsize=64)
def _texture_png(path: str) -> bytes:
    """A labmaze texture downscaled to ``TEXTURE_SIZE_PX`` (PNG bytes)."""
    from PIL import Image

    # RGBA first: some labmaze textures are palette images with transparency
    image = Image.open(path).convert("RGBA").convert("RGB").resize((TEXTURE_SIZE_PX, TEXTURE_SIZE_PX), Image.BILINEAR)
    buffer = io.BytesIO()
    image.save(buffer, format="PNG")
    return buffer.getvalue()


def house_mjcf(house: House, framebuffer_px: int = 256) -> tuple[str, dict[str, bytes]]:
    """The MJCF XML of a house and the texture files it references.

    Args:
        house: a house from :func:`build_house`.
        framebuffer_px: side of the offscreen framebuffer, pixels (the largest frame size).

    Returns:
        ``(xml, assets)`` for :meth:`mujoco.MjModel.from_xml_string`.
    """
    wall_paths = labmaze_assets.get_wall_texture_paths(house.style)
    floor_paths = labmaze_assets.get_floor_texture_paths(house.style)
    assets: dict[str, bytes] = {}
    asset_xml, body_xml = [], []
    for kind, quads_by_label, paths, names in (
        ("wall", _wall_quads(house), wall_paths, house.wall_texture_of_label),
        ("floor", _floor_quads(house), floor_paths, house.floor_texture_of_label),
    ):
        for index, label in enumerate(sorted(quads_by_label)):
            texture_name = names[label]
            file_name = f"{kind}_{texture_name}.png"
            assets[file_name] = _texture_png(paths[texture_name])
            vertex, face, texcoord = _polygon_mesh(quads_by_label[label])
            asset_xml.append(f'<texture name="{kind}{index}" type="2d" file="{file_name}"/>')
            asset_xml.append(f'<material name="{kind}{index}" texture="{kind}{index}" specular="0" shininess="0"/>')
            asset_xml.append(
                f'<mesh name="{kind}{index}" vertex="{vertex}" face="{face}" texcoord="{texcoord}" inertia="shell"/>'
            )
            body_xml.append(f'<geom type="mesh" mesh="{kind}{index}" material="{kind}{index}"/>')
    landmarks = _landmark_polygons(house)
    if landmarks:
        assets["palette.png"] = _palette_png()
        vertex, face, texcoord = _polygon_mesh(landmarks)
        asset_xml.append('<texture name="palette" type="2d" file="palette.png"/>')
        asset_xml.append('<material name="palette" texture="palette" specular="0" shininess="0"/>')
        asset_xml.append(f'<mesh name="landmarks" vertex="{vertex}" face="{face}" texcoord="{texcoord}" inertia="shell"/>')
        body_xml.append('<geom type="mesh" mesh="landmarks" material="palette"/>')
    xml = f"""<mujoco model="house_{house.seed}">
  <compiler angle="radian"/>
  <!-- extent 1: visual/map znear and zfar (relative to the extent) are then in metres -->
  <statistic extent="1" center="0 0 0"/>
  <visual>
    <global offwidth="{framebuffer_px}" offheight="{framebuffer_px}"/>
    <quality shadowsize="0" offsamples="0"/>
    <map znear="0.05" zfar="40" haze="0"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.55 0.55 0.55" specular="0 0 0"/>
  </visual>
  <default><geom contype="0" conaffinity="0"/></default>
  <asset>
    {chr(10).join("    " + line for line in asset_xml).strip()}
  </asset>
  <worldbody>
    <camera name="eye" pos="1 1 {house.eye_height_m}" fovy="{FIELD_OF_VIEW_DEG}"/>
    {chr(10).join("    " + line for line in body_xml).strip()}
  </worldbody>
</mujoco>
"""
    return xml, assets

"""The MuJoCo model of a house: one textured mesh, one texture atlas, one draw call.

:func:`house_mjcf` turns a :class:`~envs.scenes.House` layout into MJCF:

1. Wall faces that border free space (:func:`~envs.scenes.wall_faces`, collinear
   runs merged) become quads, the floor of each room becomes a few rectangles,
   furniture becomes prisms and panels single quads.
2. All of it is ONE mesh geom with ONE texture, a per-house atlas: a frame is
   one draw call with no texture switch (the cheapest for a CPU renderer).
3. The atlas holds each room's labmaze wall and floor texture repeated in a
   padded cell, and quads are cut so that none spans more than its cell, so
   textures lie exactly as ``GL_REPEAT`` would put them with one tile per
   ``TEXTURE_TILE_M`` metres. Landmarks sample one colour square of a palette cell.

The layout never sees MuJoCo: this module takes the layout. :func:`house_model`
compiles a house's model once (:func:`compile_house`, which copies the atlas in
without a PNG round trip).
"""
from __future__ import annotations

import functools
import io
import math
import weakref
from dataclasses import dataclass

import numpy as np
from labmaze import assets as labmaze_assets

from envs.scenes import FIELD_OF_VIEW_DEG, LANDMARK_PALETTE, WALL_CHAR, House, wall_faces

#: Side of a texture once downscaled for the GPU-less renderer, pixels.
TEXTURE_SIZE_PX = 128
#: Texture repeat: metres of wall or floor covered by one texture tile.
TEXTURE_TILE_M = 1.0
#: Sides of the prism drawn for a cylindrical piece of furniture.
CYLINDER_SIDES = 8
#: Width of one colour stripe in the landmark palette texture, pixels.
PALETTE_STRIPE_PX = 16
#: Texture atlas of a house (one texture for walls, floors and landmarks): tiles
#: repeated per cell along walls and both ways on floors (a quad may span that many
#: tiles), padding around each cell (the same periodic texture), cell sides rounded
#: up to a multiple of this many pixels (cells stay aligned in mipmap levels).
ATLAS_WALL_REPEATS = 2
ATLAS_FLOOR_REPEATS = 2
ATLAS_PADDING_PX = 16
ATLAS_ALIGN_PX = 32
#: Side of the offscreen framebuffer by default, pixels (the largest frame size).
DEFAULT_FRAMEBUFFER_PX = 256
#: The camera's far clipping distance, metres (a default 15 m house's diagonal is 21 m;
#: larger houses clip at their diagonal, :func:`far_clip_m`).
MIN_FAR_CLIP_M = 40


def house_mjcf(house: House, framebuffer_px: int = DEFAULT_FRAMEBUFFER_PX) -> tuple[str, dict[str, bytes]]:
    """The MJCF XML of a house and the texture file it references.

    The whole house is ONE mesh geom with ONE material: walls, floor and landmarks
    share a texture atlas (:func:`_house_atlas`), so a frame is one draw call with
    no texture switch (the cheapest for a CPU renderer).

    Args:
        house: a house from :func:`~envs.scenes.build_house`.
        framebuffer_px: side of the offscreen framebuffer, pixels (the largest frame size).

    Returns:
        ``(xml, assets)`` for :meth:`mujoco.MjModel.from_xml_string`; the atlas is
        the PNG ``assets["atlas.png"]``. :func:`house_model` compiles the same model
        without the PNG round trip.

    Examples:
        >>> from envs.scenes import build_house
        >>> xml, assets = house_mjcf(build_house(0))
        >>> sorted(assets), xml.count('<geom type="mesh"')
        (['atlas.png'], 1)
    """
    atlas = _house_atlas(house)
    xml = _house_xml(house, atlas, '<texture name="atlas" type="2d" file="atlas.png"/>', framebuffer_px)
    return xml, {"atlas.png": _atlas_png(atlas)}


def compile_house(house: House, framebuffer_px: int = DEFAULT_FRAMEBUFFER_PX):
    """The :class:`mujoco.MjModel` of :func:`house_mjcf`, with the atlas copied in directly.

    The XML declares a flat placeholder texture of the atlas's size, whose texels
    are then overwritten (MuJoCo stores a PNG's rows top first, as the atlas is),
    which skips encoding and decoding a PNG of about a megapixel.
    """
    import mujoco

    atlas = _house_atlas(house)
    height, width = atlas.pixels.shape[:2]
    placeholder = f'<texture name="atlas" type="2d" builtin="flat" width="{width}" height="{height}" rgb1="0 0 0"/>'
    model = mujoco.MjModel.from_xml_string(_house_xml(house, atlas, placeholder, framebuffer_px))
    model.tex_data[:] = atlas.pixels.reshape(-1)
    return model


#: Compiled models of the live houses, by ``id(house)``; an entry goes with its house.
_COMPILED: dict[int, object] = {}


def house_model(house: House):
    """The compiled :class:`mujoco.MjModel` of a layout (:func:`compile_house`), compiled once
    per :class:`~envs.scenes.House` object and freed with it.

    :func:`envs.scenes.build_house` caches houses by seed, so a seed's model is compiled
    once while its house is cached.

    Examples:
        >>> from envs.scenes import build_house
        >>> house = build_house(0)
        >>> house_model(house) is house_model(house), house_model(house).ntex
        (True, 1)
    """
    key = id(house)
    model = _COMPILED.get(key)
    if model is None:
        model = _COMPILED[key] = compile_house(house)
        weakref.finalize(house, _COMPILED.pop, key, None)
    return model


def far_clip_m(house: House) -> int:
    """The camera's far clipping distance, metres: :data:`MIN_FAR_CLIP_M`, or the house's diagonal if longer."""
    return max(MIN_FAR_CLIP_M, math.ceil(math.hypot(*house.size_m)))


def _house_xml(house: House, atlas: _Atlas, texture_xml: str, framebuffer_px: int) -> str:
    vertex, face, texcoord = _polygon_mesh(house_polygons(house, atlas))
    return f"""<mujoco model="house_{house.seed}">
  <compiler angle="radian"/>
  <!-- extent 1: visual/map znear and zfar (relative to the extent) are then in metres -->
  <statistic extent="1" center="0 0 0"/>
  <visual>
    <global offwidth="{framebuffer_px}" offheight="{framebuffer_px}"/>
    <quality shadowsize="0" offsamples="0"/>
    <map znear="0.05" zfar="{far_clip_m(house)}" haze="0"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.55 0.55 0.55" specular="0 0 0"/>
  </visual>
  <default><geom contype="0" conaffinity="0"/></default>
  <asset>
    {texture_xml}
    <material name="atlas" texture="atlas" specular="0" shininess="0"/>
    <mesh name="house" vertex="{vertex}" face="{face}" texcoord="{texcoord}" inertia="shell"/>
  </asset>
  <worldbody>
    <camera name="eye" pos="1 1 {house.eye_height_m}" fovy="{FIELD_OF_VIEW_DEG}"/>
    <geom type="mesh" mesh="house" material="atlas"/>
  </worldbody>
</mujoco>
"""


def _atlas_png(atlas: _Atlas) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(atlas.pixels)).save(buffer, format="PNG", compress_level=1)
    return buffer.getvalue()


def house_polygons(house: House, atlas: _Atlas | None = None) -> list[np.ndarray]:
    """Every visible polygon of a house (walls, floor, landmarks) with atlas texcoords.

    Returns:
        ``(k, 5)`` arrays of xyz + uv rows, counter-clockwise seen from the front.
    """
    atlas = _house_atlas(house) if atlas is None else atlas
    polygons: list[np.ndarray] = []
    wall_quads = _wall_quads(house)
    for label in sorted(wall_quads):
        key = ("wall", room_texture_key(house, "wall", label))
        for quad, _ in wall_quads[label]:
            polygons.append(np.concatenate([quad[:, :3], atlas.texcoords(key, quad[:, 3:])], axis=1))
    floor_quads = _floor_quads(house)
    for label in sorted(floor_quads):
        key = ("floor", room_texture_key(house, "floor", label))
        for quad in floor_quads[label]:
            polygons.append(np.concatenate([quad[:, :3], atlas.texcoords(key, quad[:, 3:])], axis=1))
    for polygon in _landmark_polygons(house):
        # _landmark_polygons gives palette-strip texcoords (u, 0.5): map the colour to the atlas
        index = int(np.floor(polygon[0, 3] * len(LANDMARK_PALETTE)))
        uv = atlas.palette_texcoords(index)
        polygons.append(np.concatenate([polygon[:, :3], np.repeat(uv[None], len(polygon), axis=0)], axis=1))
    return polygons


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
    fmt = lambda a: " ".join(f"{v:.4f}" for v in np.concatenate(a).ravel())
    return fmt(vertices), " ".join(str(v) for v in np.concatenate(faces)), fmt(texcoords)


def _cut_points(start: float, stop: float, period: float) -> np.ndarray:
    """``start``, every multiple of ``period`` strictly between, and ``stop``."""
    first = np.floor(start / period + 1e-9) + 1
    inner = np.arange(first, np.ceil(stop / period - 1e-9)) * period
    return np.concatenate([[start], inner, [stop]])


def _wall_quads(house: House) -> dict[str, list[tuple[np.ndarray, float]]]:
    """Wall faces as quads that each fit one atlas cell, by room label.

    A face's texture coordinates are those ``GL_REPEAT`` would use over the
    whole face with one texture tile per ``TEXTURE_TILE_M`` metres (u along the
    face from its start, v downwards from the top of the wall). A face longer than
    ``ATLAS_WALL_REPEATS`` tiles is cut at multiples of that many tiles, and each
    quad's texcoords are made local to its cut (the atlas cell repeats the tile).

    Returns:
        ``{label: [(quad, u_offset)]}``: ``(4, 5)`` xyz + local uv rows
        (counter-clockwise from the front) and the number of tiles removed from u.
    """
    quads: dict[str, list[tuple[np.ndarray, float]]] = {}
    height = house.wall_height_m
    t = TEXTURE_TILE_M
    v = height / t
    for p0, p1, normal, label in wall_faces(house):
        # order the bottom edge so that (edge x up) points along the normal (front face)
        edge = p1 - p0
        if edge[0] * normal[1] - edge[1] * normal[0] > 0:  # cross(edge, z) . normal must be < 0
            p0, p1 = p1, p0
        length = float(np.hypot(*(p1 - p0)))
        direction = (p1 - p0) / length
        cuts = _cut_points(0.0, length / t, ATLAS_WALL_REPEATS)
        for u0, u1 in zip(cuts[:-1], cuts[1:]):
            a, b = p0 + direction * u0 * t, p0 + direction * u1 * t
            offset = float(np.floor(u0 / ATLAS_WALL_REPEATS + 1e-9) * ATLAS_WALL_REPEATS)
            s0, s1 = u0 - offset, u1 - offset
            quad = np.array(
                [
                    [a[0], a[1], 0.0, s0, v],
                    [b[0], b[1], 0.0, s1, v],
                    [b[0], b[1], height, s1, 0.0],
                    [a[0], a[1], height, s0, 0.0],
                ]
            )
            quads.setdefault(label, []).append((quad, offset))
    return quads


def _label_rectangles(mask: np.ndarray) -> list[tuple[int, int, int, int]]:
    """Cover the True cells of a grid with rectangles ``(row, col, rows, cols)`` (greedy, row-major)."""
    mask = mask.copy()
    rectangles = []
    rows, cols = mask.shape
    for row, col in np.argwhere(mask):
        if not mask[row, col]:
            continue
        width = 1
        while col + width < cols and mask[row, col + width]:
            width += 1
        height = 1
        while row + height < rows and mask[row + height, col : col + width].all():
            height += 1
        mask[row : row + height, col : col + width] = False
        rectangles.append((int(row), int(col), height, width))
    return rectangles


def _floor_quads(house: House) -> dict[str, list[np.ndarray]]:
    """The floor of each room label as rectangles that each fit one atlas cell.

    A room's cells are merged into rectangles, cut where x / t or y / t is a
    multiple of ``ATLAS_FLOOR_REPEATS`` (t = ``TEXTURE_TILE_M``); texcoords are
    x / t and y / t made local to that cut, so the texture lies on the floor
    exactly as ``GL_REPEAT`` with one tile per t metres would put it.
    """
    quads: dict[str, list[np.ndarray]] = {}
    size = house.cell_size_m
    t = TEXTURE_TILE_M
    k = ATLAS_FLOOR_REPEATS
    labels = house.room_labels
    for label in sorted({str(x) for x in np.unique(labels)} - {WALL_CHAR}):
        for row, col, rows, cols in _label_rectangles(labels == label):
            xs = _cut_points(col * size / t, (col + cols) * size / t, k)
            ys = _cut_points(row * size / t, (row + rows) * size / t, k)
            for u0, u1 in zip(xs[:-1], xs[1:]):
                for v0, v1 in zip(ys[:-1], ys[1:]):
                    du = np.floor(u0 / k + 1e-9) * k
                    dv = np.floor(v0 / k + 1e-9) * k
                    quads.setdefault(label, []).append(
                        np.array(
                            [
                                [u0 * t, v0 * t, 0, u0 - du, v0 - dv],
                                [u1 * t, v0 * t, 0, u1 - du, v0 - dv],
                                [u1 * t, v1 * t, 0, u1 - du, v1 - dv],
                                [u0 * t, v1 * t, 0, u0 - du, v1 - dv],
                            ]
                        )
                    )
    return quads


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


def _palette_u(rgb: np.ndarray) -> float:
    index = int(np.argmin(np.abs(LANDMARK_PALETTE - rgb).sum(axis=1)))
    return (index + 0.5) / len(LANDMARK_PALETTE)


@dataclass(frozen=True)
class _Atlas:
    """A house's texture atlas.

    Attributes:
        pixels: ``(H, W, 3)`` uint8, row 0 at the top (as in a PNG file).
        origins: ``(kind, texture name)`` -> (x, y) pixel of the cell's tile origin
            (the cell's top-left corner plus the padding); kind "palette" has name "".
    """

    pixels: np.ndarray
    origins: dict[tuple[str, str], tuple[int, int]]

    def texcoords(self, key: tuple[str, str], local: np.ndarray) -> np.ndarray:
        """Atlas texcoords of tile-local ``(..., 2)`` coordinates (tile units) in a cell."""
        height, width = self.pixels.shape[:2]
        x, y = self.origins[key]
        return np.stack(
            [(x + local[..., 0] * TEXTURE_SIZE_PX) / width, (y + local[..., 1] * TEXTURE_SIZE_PX) / height], axis=-1
        )

    def palette_texcoords(self, index: int) -> np.ndarray:
        """Atlas texcoords of the centre of a palette colour's square."""
        height, width = self.pixels.shape[:2]
        x, y = self.origins[("palette", "")]
        return np.array([(x + (index + 0.5) * PALETTE_STRIPE_PX) / width, (y + 0.5 * PALETTE_STRIPE_PX) / height])


def _house_atlas(house: House) -> _Atlas:
    """Every wall and floor texture of a house and the landmark palette in one atlas.

    Cells, packed in rows (walls, floors, palette): a wall cell repeats its tile
    ``ATLAS_WALL_REPEATS`` times along u and over the wall's height along v, a
    floor cell ``ATLAS_FLOOR_REPEATS`` times both ways. Each cell is surrounded by
    ``ATLAS_PADDING_PX`` pixels of the same periodic texture, so bilinear
    filtering and mipmap levels up to log2(padding) never mix two textures;
    coarser levels (far, grazing surfaces) may blend neighbouring cells slightly.
    """
    wall_paths = labmaze_assets.get_wall_texture_paths(house.style)
    floor_paths = labmaze_assets.get_floor_texture_paths(house.style)
    shelves: list[list[tuple[tuple[str, str], np.ndarray]]] = []
    for kind, names, paths, repeats in (
        ("wall", house.wall_texture_of_label, wall_paths, (ATLAS_WALL_REPEATS, house.wall_height_m / TEXTURE_TILE_M)),
        ("floor", house.floor_texture_of_label, floor_paths, (ATLAS_FLOOR_REPEATS, ATLAS_FLOOR_REPEATS)),
    ):
        shelf = []
        for key in sorted({room_texture_key(house, kind, label) for label in names}):
            name, _, hue = key.partition(PAINT_KEY_SEPARATOR)
            cell = _tiled_cell(paths[name], *repeats) if not hue else _painted_cell(paths[name], *repeats, float(hue))
            shelf.append(((kind, key), cell))
        shelves.append(shelf)
    palette = _palette_cell()
    shelves.append([(("palette", ""), palette)])
    width = max(sum(cell.shape[1] for _, cell in shelf) for shelf in shelves)
    height = sum(max(cell.shape[0] for _, cell in shelf) for shelf in shelves)
    pixels = np.zeros((height, width, 3), dtype=np.uint8)
    origins: dict[tuple[str, str], tuple[int, int]] = {}
    y = 0
    for shelf in shelves:
        x = 0
        for key, cell in shelf:
            pixels[y : y + cell.shape[0], x : x + cell.shape[1]] = cell
            pad = 0 if key[0] == "palette" else ATLAS_PADDING_PX
            origins[key] = (x + pad, y + pad)
            x += cell.shape[1]
        y += max(cell.shape[0] for _, cell in shelf)
    pixels.setflags(write=False)
    return _Atlas(pixels=pixels, origins=origins)


@functools.lru_cache(maxsize=64)
def _texture_pixels(path: str) -> np.ndarray:
    """A labmaze texture downscaled to ``TEXTURE_SIZE_PX`` (``(T, T, 3)`` uint8, row 0 at the top)."""
    from PIL import Image

    # RGBA first: some labmaze textures are palette images with transparency
    image = Image.open(path).convert("RGBA").convert("RGB").resize((TEXTURE_SIZE_PX, TEXTURE_SIZE_PX), Image.BILINEAR)
    pixels = np.asarray(image, dtype=np.uint8)
    pixels.setflags(write=False)
    return pixels


def _round_up(value: float, multiple: int) -> int:
    return int(np.ceil(value / multiple - 1e-9) * multiple)


@functools.lru_cache(maxsize=256)
def _tiled_cell(path: str, repeats_u: float, repeats_v: float) -> np.ndarray:
    """An atlas cell: a texture's tile repeated ``repeats_u`` x ``repeats_v`` times, from ``ATLAS_PADDING_PX`` in.

    The whole cell is the tile's periodic extension, so the padding around the
    used area holds the texels ``GL_REPEAT`` would fetch there. Sides are rounded
    up to multiples of ``ATLAS_ALIGN_PX`` so that cells stay aligned in mipmaps.
    Cached (read-only): houses of a style share their textures.
    """
    tile = _texture_pixels(path)
    size = TEXTURE_SIZE_PX
    pad = ATLAS_PADDING_PX
    width = _round_up(repeats_u * size + 2 * pad, ATLAS_ALIGN_PX)
    height = _round_up(repeats_v * size + 2 * pad, ATLAS_ALIGN_PX)
    start = (-pad) % size  # texel of the tile at the cell's first row / column
    reps_y = -(-(start + height) // size)
    reps_x = -(-(start + width) // size)
    cell = np.tile(tile, (reps_y, reps_x, 1))[start : start + height, start : start + width]
    cell = np.ascontiguousarray(cell)
    cell.setflags(write=False)
    return cell


#: Saturation of a repainted room's colour (:attr:`~envs.scenes.House.paint`; value: the texture's luminance).
PAINT_SATURATION = 0.6
#: Separates a texture's name from a repainted room's hue in an atlas key.
PAINT_KEY_SEPARATOR = "#hue="


def room_texture_key(house: House, kind: str, label: str) -> str:
    """The atlas key of a room's ``kind`` (``"wall"`` or ``"floor"``) texture: its labmaze texture's
    name, and for a repainted room (:attr:`~envs.scenes.House.paint`) the new hue after
    :data:`PAINT_KEY_SEPARATOR`.

    Examples:
        >>> from envs.scenes import build_house, with_paint
        >>> house = build_house(0)
        >>> room_texture_key(with_paint(house, {"A": (0.25, 0.5)}), "floor", "A").endswith("#hue=0.500000")
        True
    """
    names = house.wall_texture_of_label if kind == "wall" else house.floor_texture_of_label
    hues = house.paint.get(label)
    if hues is None:
        return names[label]
    return f"{names[label]}{PAINT_KEY_SEPARATOR}{hues[0 if kind == 'wall' else 1]:.6f}"


@functools.lru_cache(maxsize=256)
def _painted_cell(path: str, repeats_u: float, repeats_v: float, hue: float) -> np.ndarray:
    """:func:`_tiled_cell` repainted: each texel's luminance times a colour of ``hue`` (saturation
    :data:`PAINT_SATURATION`) of the same luminance, so the pattern stays and the colour is new."""
    import colorsys

    cell = _tiled_cell(path, repeats_u, repeats_v).astype(np.float32)
    weights = np.array([0.299, 0.587, 0.114], dtype=np.float32)
    colour = np.array(colorsys.hsv_to_rgb(hue % 1.0, PAINT_SATURATION, 1.0), dtype=np.float32)
    painted = (cell @ weights)[..., None] * (colour / float(colour @ weights))
    painted = np.clip(np.rint(painted), 0, 255).astype(np.uint8)
    painted.setflags(write=False)
    return painted


def _palette_cell() -> np.ndarray:
    """Atlas cell of the landmark palette: one ``PALETTE_STRIPE_PX`` square per colour, side by side."""
    stripes = np.repeat((LANDMARK_PALETTE * 255).astype(np.uint8), PALETTE_STRIPE_PX, axis=0)
    return np.repeat(stripes[None], PALETTE_STRIPE_PX, axis=0)

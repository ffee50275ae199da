"""Tests for envs.scenes: determinism, splits, landmarks, maps."""
from __future__ import annotations

import numpy as np
import pytest

from envs.house_mesh import house_mjcf, house_model
from envs.render import FirstPersonRenderer, draw_top_down_map
from envs.scenes import DEFAULT_SPLIT_SIZES, build_house, split_seeds


def test_house_is_a_pure_function_of_its_seed():
    build_house.cache_clear()
    first_xml, first_assets = house_mjcf(build_house(5))
    build_house.cache_clear()
    second_xml, second_assets = house_mjcf(build_house(5))
    assert first_xml == second_xml
    assert first_assets.keys() == second_assets.keys()
    assert house_mjcf(build_house(6))[0] != first_xml


def test_splits_are_disjoint_and_enlargeable():
    splits = {name: set(split_seeds(name)) for name in ("train", "val", "test")}
    assert {k: len(v) for k, v in splits.items()} == DEFAULT_SPLIT_SIZES
    assert not splits["train"] & splits["val"] and not splits["train"] & splits["test"]
    assert not splits["val"] & splits["test"]
    bigger = split_seeds("train", 500)
    assert bigger[:61] == split_seeds("train") and len(set(bigger)) == 500
    assert not set(bigger) & set(split_seeds("val", 500))


@pytest.mark.parametrize("bad", ["training", "", "TEST"])
def test_unknown_split_is_refused(bad):
    with pytest.raises(ValueError, match="split must be one of"):
        split_seeds(bad)


@pytest.mark.parametrize("bad", [0, -3, 2.5])
def test_bad_house_count_is_refused(bad):
    with pytest.raises(ValueError, match="num_houses"):
        split_seeds("train", bad)


def test_house_has_rooms_furniture_and_one_navigable_component():
    house = build_house(0)
    rooms = {str(x) for x in np.unique(house.room_labels)} - {"*", "."}
    assert len(rooms) >= 3
    assert house.furniture and house.panels
    assert house.graph.components() == 1
    # every room gets its own wall texture (as far as the style has textures)
    assert len(set(house.wall_texture_of_label.values())) >= min(len(rooms), 4)
    # a compiled model draws the house with few geoms
    assert house_model(house).ngeom <= 2 * (len(rooms) + 2) + 2


def test_house_is_one_textured_mesh_and_model_matches_its_mjcf():
    import mujoco

    house = build_house(3)
    model = house_model(house)
    assert model.ngeom == 1 and model.ntex == 1 and model.nmat == 1
    xml, assets = house_mjcf(house)
    reference = mujoco.MjModel.from_xml_string(xml, assets)  # through the atlas PNG
    for name in ("tex_data", "tex_width", "tex_height", "mesh_vert", "mesh_texcoord", "mesh_face"):
        assert np.array_equal(getattr(model, name), getattr(reference, name)), name


def test_atlas_quads_stay_inside_their_cells():
    """Every wall and floor quad samples one atlas cell (no GL_REPEAT across tiles)."""
    from envs import house_mesh

    house = build_house(0)
    height_tiles = house.wall_height_m / house_mesh.TEXTURE_TILE_M
    for quads in house_mesh._wall_quads(house).values():
        uv = np.stack([quad[:, 3:] for quad, _ in quads])
        assert uv[..., 0].min() >= 0 and uv[..., 0].max() <= house_mesh.ATLAS_WALL_REPEATS + 1e-9
        assert uv[..., 1].min() >= 0 and uv[..., 1].max() <= height_tiles + 1e-9
    floor_cells = 0
    for quads in house_mesh._floor_quads(house).values():
        uv = np.stack([quad[:, 3:] for quad in quads])
        assert uv.min() >= 0 and uv.max() <= house_mesh.ATLAS_FLOOR_REPEATS + 1e-9
        floor_cells += sum(np.prod(quad[2, :2] - quad[0, :2]) for quad in quads)
    assert floor_cells == pytest.approx((~house.walls).sum() * house.cell_size_m**2)  # the floor is covered once
    atlas = house_mesh._house_atlas(house)
    pixels = np.concatenate([polygon[:, 3:] for polygon in house_mesh.house_polygons(house, atlas)]) * atlas.pixels.shape[1::-1]
    assert pixels.min() >= 0 and (pixels <= atlas.pixels.shape[1::-1]).all()


def test_frames_from_two_rooms_differ():
    house = build_house(0)
    renderer = FirstPersonRenderer(64, 64)
    labels = house.room_labels
    rooms = sorted({str(x) for x in np.unique(labels)} - {"*", "."})
    views = []
    for room in rooms[:2]:
        rows, cols = np.nonzero(labels == room)
        centre = np.array([cols.mean() + 0.5, rows.mean() + 0.5])
        frames = [renderer.render(house, np.array([*centre, h])) for h in np.linspace(0, 2 * np.pi, 4, endpoint=False)]
        views.append(np.stack(frames).astype(np.float64))
    renderer.close()
    # mean colour of the views differs clearly between the rooms
    assert np.abs(views[0].mean(axis=(0, 1, 2)) - views[1].mean(axis=(0, 1, 2))).max() > 8.0
    assert views[0].std() > 10 and views[1].std() > 10  # not a blank frame


def test_top_down_map_draws_paths():
    import matplotlib.pyplot as plt

    house = build_house(1)
    path = np.array([house.spawn_xy, house.spawn_xy + [0.5, 0.0]])
    ax = draw_top_down_map(house, paths={"demo": path}, points={"memory": path[:1]})
    assert ax.get_xlim() == (0.0, house.size_m[0])
    lines = [line for line in ax.get_lines() if line.get_label() == "demo"]
    assert len(lines) == 1 and np.allclose(lines[0].get_xydata(), path)
    plt.close(ax.figure)

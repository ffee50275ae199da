"""Tests for envs.demo_store (DemoStore) and PathFollowEnv's store mode (demo_store, emit_demo_frames)."""
from __future__ import annotations

import json
import os
import pickle
import shutil
from functools import partial

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.collectors import Collector
from torchrl.envs import ParallelEnv, SerialEnv, check_env_specs

from envs import demo_store as demo_store_module
from envs.demo_store import DemoStore, DemoStoreConfig, DemoStoreError, sample_store_demonstration
from envs.episode_spec import EpisodeSpec
from envs.factory import make_path_follow_env
from envs.nav_env import PathFollowEnv
from envs.render import FirstPersonRenderer
from envs.scenes import build_house, split_seeds
from envs.version import ENV_VERSION
from envs.worker_processes import start_method
from spf_rl.modules import SPFConfig, make_actor, make_spf_policy

# K = 20 so that two env seeds drawing the same sequence of demo ids is unlikely
STORE_CONFIG = DemoStoreConfig(episodes=EpisodeSpec(split="train", num_houses=2, demo_length=5, image_size=32, seed=0), num_demos=20)
ENV_KWARGS = dict(num_houses=2, demo_length=5, image_size=32, max_steps=3)
TENSOR_FILES = ("frames", "actions", "poses", "house_seed", "shortest_length_m")


@pytest.fixture(scope="module")
def store_root(tmp_path_factory):
    """Directory of a store of STORE_CONFIG, shared by the module's tests (never modified)."""
    root = tmp_path_factory.mktemp("demo_store") / "store"
    DemoStore.build(root, STORE_CONFIG, progress=False)
    return root


@pytest.fixture(scope="module")
def store(store_root):
    return DemoStore(store_root)


@pytest.fixture
def store_copy(store_root, tmp_path):
    """A private copy of the shared store, free to be damaged."""
    copy = tmp_path / "copy"
    shutil.copytree(store_root, copy)
    return copy


def _tensors(store: DemoStore) -> dict[str, torch.Tensor]:
    return {
        "frames": store.frames,
        "actions": store.actions,
        "poses": store.poses,
        "house_seed": store.house_seeds,
        "shortest_length_m": store.shortest_lengths_m,
    }


# ------------------------------------------------------------------ building
def test_build_is_deterministic_and_depends_on_the_seed(store, tmp_path):
    config = DemoStoreConfig.from_dict({**STORE_CONFIG.to_dict(), "num_demos": 4})
    first = DemoStore.build(tmp_path / "a", config, progress=False)
    second = DemoStore.build(tmp_path / "b", DemoStoreConfig.from_dict(config.to_dict()), progress=False)
    for key, value in _tensors(first).items():
        assert torch.equal(value, _tensors(second)[key]), key
    # demonstration k depends only on (seed, k): a smaller store is a prefix of a larger one
    for key, value in _tensors(first).items():
        assert torch.equal(value, _tensors(store)[key][:4]), key
    assert first.frames.float().std() > 10  # rendered, not blank
    other = DemoStore.build(tmp_path / "c", DemoStoreConfig.from_dict({**config.to_dict(), "seed": 1}), progress=False)
    assert not torch.equal(other.poses, first.poses)
    assert not torch.equal(other.frames, first.frames)


def test_stored_demonstrations_match_their_source(store):
    config = store.config
    assert store.frames.shape == (20, 5, 32, 32, 3) and store.frames.dtype == torch.uint8
    assert store.poses.shape == (20, 6, 3) and store.actions.shape == (20, 5) and len(store) == 20
    assert set(store.house_seeds.tolist()) <= set(split_seeds("train", 2))
    renderer = FirstPersonRenderer(32, 32)
    try:
        for k in (0, 7, 19):
            demo = sample_store_demonstration(config, k)
            assert int(store.house_seeds[k]) == demo.house_seed
            assert torch.equal(store.poses[k], torch.from_numpy(demo.poses))
            assert torch.equal(store.actions[k], torch.from_numpy(demo.actions))
            assert float(store.shortest_lengths_m[k]) == demo.shortest_length_m
            house = build_house(demo.house_seed)
            for i in (0, 4):
                frame = renderer.render(house, store.poses[k][i].numpy())
                assert torch.equal(store.frames[k][i], torch.from_numpy(frame)), (k, i)
    finally:
        renderer.close()
    # frames differ along a route and between routes
    assert not torch.equal(store.frames[0][0], store.frames[0][4])
    assert not torch.equal(store.frames[0], store.frames[7])


def test_demonstration_has_the_stored_route(store):
    demo = store.demonstration(3)
    assert demo.house_seed == int(store.house_seeds[3])
    np.testing.assert_array_equal(demo.poses, store.poses[3].numpy())
    np.testing.assert_array_equal(demo.actions, store.actions[3].numpy())
    assert demo.end_field.at(demo.poses[-1][:2]) == pytest.approx(0.0, abs=0.2)
    assert demo.end_field.at(demo.poses[0][:2]) == pytest.approx(demo.shortest_length_m, rel=0.05, abs=0.2)


def test_build_reopens_a_matching_store_and_refuses_another_config(store_root):
    frames_file = store_root / "data" / "frames.memmap"
    before = (frames_file.stat().st_mtime_ns, (store_root / "meta.json").stat().st_mtime_ns)
    reopened = DemoStore.build(store_root, DemoStoreConfig.from_dict(STORE_CONFIG.to_dict()), progress=False)
    assert (frames_file.stat().st_mtime_ns, (store_root / "meta.json").stat().st_mtime_ns) == before
    assert reopened.config == STORE_CONFIG and len(reopened) == 20
    with pytest.raises(DemoStoreError, match=str(store_root)):
        DemoStore.build(store_root, DemoStoreConfig.from_dict({**STORE_CONFIG.to_dict(), "seed": 5}), progress=False)
    with pytest.raises(DemoStoreError, match=str(store_root)):
        DemoStore.build(store_root, DemoStoreConfig.from_dict({**STORE_CONFIG.to_dict(), "num_demos": 3}), progress=False)


def test_interrupted_build_resumes_to_the_same_bytes(tmp_path, monkeypatch):
    config = DemoStoreConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, image_size=32), num_demos=5)
    monkeypatch.setattr(demo_store_module, "DEMO_CHUNK_ROWS", 2)  # chunks {0, 1}, {2, 3}, {4}
    reference = DemoStore.build(tmp_path / "reference", config, progress=False)
    root = tmp_path / "store"
    real = demo_store_module.sample_store_demonstration
    calls: list[int] = []

    def failing(config, index):
        calls.append(index)
        if index == 3:
            raise KeyboardInterrupt
        return real(config, index)

    monkeypatch.setattr(demo_store_module, "sample_store_demonstration", failing)
    with pytest.raises(KeyboardInterrupt):
        DemoStore.build(root, config, progress=False)
    assert not root.exists() and (tmp_path / "store.partial").exists()  # root only ever holds a whole store
    with pytest.raises(DemoStoreError, match="resume"):
        DemoStore(root)
    monkeypatch.setattr(demo_store_module, "sample_store_demonstration", lambda c, i: calls.append(i) or real(c, i))
    calls.clear()
    store = DemoStore.build(root, config, progress=False)
    assert calls == [2, 3, 4]  # chunk 0 was kept, chunk 1 redone
    assert sorted(os.listdir(tmp_path)) == ["reference", "store"]
    for key, value in _tensors(reference).items():
        assert torch.equal(_tensors(store)[key], value), key
    DemoStore(root)  # complete and verified


def test_building_and_opening_never_hold_the_full_size_layout_in_memory(tmp_path, monkeypatch):
    """The store's full-size zeros (gigabytes for a route dataset) are only ever made as meta
    tensors; its files start zero-filled."""
    config = DemoStoreConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, image_size=32), num_demos=5)
    monkeypatch.setattr(demo_store_module, "DEMO_CHUNK_ROWS", 2)
    real, devices = DemoStore.empty, []

    def recording(config):
        layout = real(config)
        devices.append((len(layout), layout["frames"].device.type))
        return layout

    monkeypatch.setattr(DemoStore, "empty", staticmethod(recording))
    assert DemoStore.layout(config)["frames"].shape == (5, 5, 32, 32, 3) and DemoStore.layout(config)["frames"].is_meta
    devices.clear()
    store = DemoStore.build(tmp_path / "store", config, progress=False)
    DemoStore(tmp_path / "store")
    assert {device for rows, device in devices if rows == 5} == {"meta"}  # build, then open: shapes only
    assert all(store.frames[row].any() for row in range(5))
    partial = DemoStore.layout(config).memmap_like(tmp_path / "fresh")
    assert not partial["frames"].any() and not partial["poses"].any()


def test_a_damaged_partial_build_is_rebuilt(tmp_path, monkeypatch):
    config = DemoStoreConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, image_size=32), num_demos=3)
    partial = tmp_path / "store.partial"
    partial.mkdir()
    (partial / "progress.json").write_text("{ not json")
    store = DemoStore.build(tmp_path / "store", config, progress=False)
    assert len(store) == 3 and not partial.exists()


def test_build_into_an_empty_existing_directory(tmp_path):
    root = tmp_path / "store"
    root.mkdir()
    store = DemoStore.build(root, DemoStoreConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, image_size=32), num_demos=2), progress=False)
    assert (root / "meta.json").exists() and len(store) == 2


# ---------------------------------------------------------------- corruption
@pytest.mark.parametrize("name", TENSOR_FILES)
def test_flipped_byte_is_detected(store_copy, name):
    path = store_copy / "data" / f"{name}.memmap"
    data = bytearray(path.read_bytes())
    data[len(data) // 2 + 1] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(DemoStoreError, match=f"'{name}'"):
        DemoStore(store_copy)
    DemoStore(store_copy, verify=False)  # only the checksums can tell


@pytest.mark.parametrize(
    "damage",
    [
        pytest.param(lambda root: os.truncate(root / "data" / "frames.memmap", 1000), id="truncated-frames"),
        pytest.param(lambda root: os.truncate(root / "data" / "poses.memmap", 0), id="emptied-poses"),
        pytest.param(lambda root: (root / "data" / "actions.memmap").unlink(), id="deleted-actions"),
        pytest.param(lambda root: (root / "meta.json").unlink(), id="deleted-meta"),
        pytest.param(lambda root: (root / "meta.json").write_text("{ not json"), id="garbage-meta"),
        pytest.param(lambda root: (root / "meta.json").write_text(""), id="empty-meta"),
        pytest.param(lambda root: (root / "data" / "meta.json").write_text("]"), id="garbage-tensordict-meta"),
        pytest.param(lambda root: shutil.rmtree(root / "data"), id="deleted-data"),
        pytest.param(lambda root: _edit_meta(root, format_version=99), id="other-format-version"),
        pytest.param(lambda root: _edit_meta(root, config={**STORE_CONFIG.to_dict(), "num_demos": 21}), id="wrong-shape"),
        pytest.param(lambda root: _edit_meta(root, config={**STORE_CONFIG.to_dict(), "split": "nope"}), id="invalid-config"),
        pytest.param(lambda root: _edit_meta(root, checksums=None), id="no-checksums"),
        # non-UTF-8 bytes and valid JSON that is not an object
        pytest.param(
            lambda root: (root / "meta.json").write_bytes(b"\xff\xfe\x00garbage"),
            id="binary-meta",
        ),
        pytest.param(
            lambda root: (root / "meta.json").write_text("[1, 2]"),
            id="json-list-meta",
        ),
    ],
)
def test_damaged_store_raises_demo_store_error(store_copy, damage):
    damage(store_copy)
    with pytest.raises(DemoStoreError, match=str(store_copy)):
        DemoStore(store_copy)


def _edit_meta(root, **changes):
    meta = json.loads((root / "meta.json").read_text())
    meta.update(changes)
    (root / "meta.json").write_text(json.dumps(meta))


@pytest.mark.parametrize(
    "changes, match",
    [
        (dict(format_version=1), "version 1 stored CHW frames"),
        (dict(env_version=1), f"made by env version 1, but this env is version {ENV_VERSION}"),
    ],
    ids=["old-layout", "old-env"],
)
def test_stale_stores_are_refused(store_copy, changes, match):
    _edit_meta(store_copy, **changes)
    with pytest.raises(DemoStoreError, match=match):
        DemoStore(store_copy)


def test_missing_store_raises_demo_store_error(tmp_path):
    with pytest.raises(DemoStoreError, match="no meta.json"):
        DemoStore(tmp_path / "nowhere")
    with pytest.raises(DemoStoreError):
        DemoStore(tmp_path)  # an existing directory that is not a store


def test_a_file_is_not_a_store(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(DemoStoreError):
        DemoStore(tmp_path / "file")


def test_build_refuses_a_non_empty_directory_that_is_not_a_store(tmp_path):
    root = tmp_path / "store"
    (root / "data").mkdir(parents=True)
    with pytest.raises(DemoStoreError, match=str(root)):
        DemoStore.build(root, DemoStoreConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, image_size=32), num_demos=1), progress=False)
    assert (root / "data").exists() and not (tmp_path / "store.partial").exists()


# ------------------------------------------------------------------ pickling
def test_store_pickles_as_its_path(store):
    payload = pickle.dumps(store)
    assert len(payload) < 10_000  # the 300 kB of frames are not inside
    clone = pickle.loads(payload)
    assert clone.root == store.root and clone.config == store.config
    for key, value in _tensors(store).items():
        assert torch.equal(_tensors(clone)[key], value), key


# ------------------------------------------------------------- lookup module
def test_lookup_by_ids(store):
    ids = torch.tensor([[3], [0], [19], [3]])
    frames = store.lookup(ids)
    assert frames.shape == (4, 5, 32, 32, 3) and frames.dtype == torch.uint8
    assert torch.equal(frames, store.frames[ids.squeeze(-1)])
    # a [B, T, 1] batch of ids (a collected batch) and a single [1] id (an unbatched env)
    batch = torch.tensor([[[1], [2], [3]], [[4], [5], [6]]])
    assert torch.equal(store.lookup(batch)[1, 2], store.frames[6])
    assert torch.equal(store.lookup(torch.tensor([7])), store.frames[7])
    # the looked-up frames are copies: a policy normalising them in place leaves the store intact
    expected = store.frames[3].clone()
    frames.zero_()
    assert torch.equal(store.frames[3], expected)


@pytest.mark.parametrize("bad", [[20], [-1], [0, 25]])
def test_lookup_refuses_out_of_range_ids(store, bad):
    with pytest.raises(ValueError, match="demo_id"):
        store.lookup(torch.tensor(bad).unsqueeze(-1))


@pytest.mark.parametrize("shape", [(), (2,), (3, 2)])
def test_lookup_refuses_ids_without_the_trailing_unit_dim(store, shape):
    with pytest.raises(ValueError, match=r"demo_id must have shape \[\*, 1\]"):
        store.lookup(torch.zeros(shape, dtype=torch.int64))


def test_lookup_module_feeds_frames_to_the_policy_only(store):
    mean = TensorDictModule(lambda frames: frames.float().mean((-4, -3, -2, -1)).unsqueeze(-1), ["demo_frames"], ["out"])
    policy = TensorDictSequential(store.lookup_module(), mean, selected_out_keys=["out"])
    ids = torch.tensor([[5], [11], [0]])
    td = TensorDict({"demo_id": ids, "pixels": torch.zeros(3, 32, 32, 3, dtype=torch.uint8)}, batch_size=[3])
    out = policy(td)
    assert "demo_frames" not in out.keys() and "out" in out.keys() and "pixels" in out.keys()
    expected = store.frames[ids.squeeze(-1)].float().mean((-4, -3, -2, -1)).unsqueeze(-1)
    torch.testing.assert_close(out["out"], expected)
    assert len(set(out["out"].squeeze(-1).tolist())) == 3  # three different demonstrations


# ------------------------------------------------------------- env: specs
@pytest.mark.parametrize("emit", [True, False])
@pytest.mark.parametrize("num_agents", [None, 3])
def test_store_env_specs(store_root, emit, num_agents):
    env = make_path_follow_env(demo_store=str(store_root), emit_demo_frames=emit, num_agents=num_agents, **ENV_KWARGS)
    env.set_seed(0)
    check_env_specs(env)
    keys = env.observation_spec.keys()
    assert "demo_id" in keys and ("demo_frames" in keys) == emit
    env.close()


def test_store_env_specs_serial_and_parallel(store_root):
    factory = partial(make_path_follow_env, demo_store=str(store_root), emit_demo_frames=False, **ENV_KWARGS)
    serial = SerialEnv(2, factory)
    parallel = ParallelEnv(2, factory, mp_start_method=start_method())
    try:
        for env in (serial, parallel):
            env.set_seed(0)
            check_env_specs(env)
        rollout = parallel.rollout(4, break_when_any_done=False)
        assert rollout["demo_id"].shape == (2, 4, 1) and "demo_frames" not in rollout.keys(True)
        ids = rollout["demo_id"].reshape(-1)
        assert ((0 <= ids) & (ids < 20)).all()
        assert torch.equal(rollout["demo_actions"], store_actions(store_root)[rollout["demo_id"].squeeze(-1)])
    finally:
        serial.close(raise_if_closed=False)
        parallel.close(raise_if_closed=False)


def store_actions(root) -> torch.Tensor:
    return DemoStore(root, verify=False).actions


# --------------------------------------------------------- env: semantics
def test_reset_emits_the_stored_demonstration(store, store_root):
    env = PathFollowEnv(demo_store=store, **ENV_KWARGS)
    env.set_seed(2)
    td = env.reset()
    k = int(td["demo_id"].item())
    assert 0 <= k < len(store)
    assert td["demo_id"].shape == (1,) and td["demo_id"].dtype == torch.int64
    assert torch.equal(td["demo_frames"], store.frames[k])
    assert torch.equal(td["pixels"], store.frames[k][0])
    assert torch.equal(td["demo_actions"], store.actions[k])
    assert td["pose"].dtype == torch.float32
    torch.testing.assert_close(td["pose"], store.poses[k][0].float())
    assert env.demonstrations[0].house_seed == int(store.house_seeds[k])
    # the emitted frames are the env's copies, not views of the store's memory map
    expected = store.frames[k].clone()
    td["demo_frames"].zero_()
    td["pixels"].zero_()
    assert torch.equal(store.frames[k], expected)

    lean = PathFollowEnv(demo_store=store_root, emit_demo_frames=False, **ENV_KWARGS)
    lean.set_seed(2)
    td = lean.reset()
    assert "demo_frames" not in td.keys() and "demo_frames" not in lean.observation_spec.keys()
    assert int(td["demo_id"].item()) == k  # the same seed draws the same demonstration
    assert torch.equal(td["pixels"], store.frames[k][0])
    td["action"] = torch.tensor(0)
    out = lean.step(td)
    assert "demo_frames" not in out.keys(True) and int(out["next", "demo_id"].item()) == k
    assert torch.equal(out["next", "demo_actions"], store.actions[k])


def _demo_ids(store, seed, num_agents=None, emit=True, steps=13):
    env = make_path_follow_env(demo_store=store, emit_demo_frames=emit, num_agents=num_agents, **ENV_KWARGS)
    env.set_seed(seed)
    torch.manual_seed(0)
    rollout = env.rollout(steps, break_when_any_done=False)
    env.close()
    return rollout


def test_same_seed_same_demonstrations_over_episodes(store):
    a, b, c = _demo_ids(store, 3), _demo_ids(store, 3, emit=False), _demo_ids(store, 4)
    ids = a["demo_id"].squeeze(-1)
    # max_steps=3: 13 steps span at least 5 episodes, each with its demonstration
    starts = a["is_init"].squeeze(-1)
    assert int(starts.sum()) >= 5  # episodes may also end early, on success
    assert len(set(ids[starts].tolist())) > 1
    assert torch.equal(ids, b["demo_id"].squeeze(-1))
    assert not torch.equal(ids, c["demo_id"].squeeze(-1))
    # every step carries its episode's stored demonstration, also after the automatic resets
    assert torch.equal(a["demo_frames"], store.frames[ids])
    assert torch.equal(a["demo_actions"], store.actions[ids])
    assert torch.equal(a["pixels"][starts], store.frames[ids[starts], 0])
    assert "demo_frames" not in b.keys(True)


def test_batched_store_env_draws_per_agent(store):
    rollout = _demo_ids(store, 5, num_agents=3, emit=False, steps=7)
    ids = rollout["demo_id"].squeeze(-1)
    assert ids.shape == (3, 7) and ((0 <= ids) & (ids < 20)).all()
    assert len(set(ids.reshape(-1).tolist())) > 3
    assert torch.equal(rollout["demo_actions"], store.actions[ids])


# ----------------------------------------------------------- env: bad input
@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(split="val"), "split"),
        (dict(num_houses=3), "num_houses"),
        (dict(demo_length=6), "demo_length"),
        (dict(image_size=64), "image_size"),
        (dict(house_seeds=[0, 1]), "house_seeds"),
        (dict(success_radius_m=1.0), "success_radius_m"),  # routes may start inside a 1 m radius
    ],
)
def test_env_refuses_a_mismatching_store(store, kwargs, match):
    with pytest.raises(ValueError, match=match):
        PathFollowEnv(demo_store=store, **{**ENV_KWARGS, **kwargs})


def test_env_refuses_emit_false_without_store_and_a_missing_store(tmp_path):
    with pytest.raises(ValueError, match="emit_demo_frames=False needs a demo_store .*or render=False"):
        PathFollowEnv(emit_demo_frames=False, **ENV_KWARGS)
    with pytest.raises(DemoStoreError):
        PathFollowEnv(demo_store=tmp_path / "nowhere", **ENV_KWARGS)
    with pytest.raises(ValueError, match="demo_store must be"):
        PathFollowEnv(demo_store=5, **ENV_KWARGS)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(num_demos=0), "num_demos"),
        (dict(num_demos=True), "num_demos"),
        (dict(demo_length=-1), "demo_length"),
        (dict(image_size=0), "image_size"),
        (dict(split="validation"), "split"),
        (dict(num_houses=0), "num_houses"),
        (dict(seed=-1), "seed"),
        (dict(seed=0.5), "seed"),
        (dict(min_route_length_m=-1.0), "min_route_length_m"),
    ],
)
def test_store_config_refuses_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        DemoStoreConfig.from_dict(kwargs)


# ---------------------------------------------------------------- collector
def test_collector_with_spf_policy_looks_frames_up(store, store_root):
    torch.manual_seed(0)
    spf = make_spf_policy(SPFConfig(demo_length=5, sparsity=0.4, feature_dim=8, hidden_size=8, image_size=(32, 32))).eval()
    actor = make_actor(spf, 3)
    policy = TensorDictSequential(store.lookup_module(), actor, selected_out_keys=list(actor.out_keys))
    assert "demo_id" in policy.in_keys and "demo_frames" not in policy.in_keys
    env = make_path_follow_env(demo_store=store_root, emit_demo_frames=False, num_agents=2, **ENV_KWARGS)
    env.append_transform(spf.make_tensordict_primer())
    env.set_seed(0)
    collector = Collector(env, policy, frames_per_batch=20, total_frames=20, auto_register_policy_transforms=False)
    try:
        batches = list(collector)
    finally:
        collector.shutdown()
    assert len(batches) == 1
    batch = batches[0]
    assert batch.batch_size == (2, 10)
    assert "demo_id" in batch.keys() and "demo_frames" not in batch.keys(True)
    action = batch["action"]
    assert action.dtype == torch.int64 and ((0 <= action) & (action < 3)).all()
    ids = batch["demo_id"]
    assert ((0 <= ids) & (ids < 20)).all()
    # the policy saw the stored frames: its first-step logits are those of the SPF policy fed the
    # looked-up frames directly (the recurrent state starts at zero)
    first = batch[:, 0]
    assert first["is_init"].all()
    direct = spf(
        TensorDict(
            {
                "pixels": first["pixels"],
                "demo_frames": store.frames[first["demo_id"].squeeze(-1)],
                "demo_actions": first["demo_actions"],
                "is_init": first["is_init"],
            },
            batch_size=[2],
        )
    )
    torch.testing.assert_close(first["next", "memory_features"], direct["next", "memory_features"])
    torch.testing.assert_close(first["logits"], direct["logits"])
    assert first["next", "memory_features"].abs().sum() > 0


# ------------------------------------------------- env: protocol on stored routes
def test_expert_follows_stored_routes_to_success(store):
    """The stored route's end, distance field and success radius agree: the noise-free expert succeeds."""
    env = make_path_follow_env(
        noise="none", demo_store=store, emit_demo_frames=False, with_expert=True, num_agents=4, **{**ENV_KWARGS, "max_steps": 20}
    )
    env.set_seed(3)
    td = env.reset()
    finished = []
    for _ in range(60):
        td.set("action", td.get("expert_action"))
        td, td_next = env.step_and_maybe_reset(td)
        done = td.get(("next", "done")).squeeze(-1)
        finished += td.get(("next", "success")).squeeze(-1)[done].tolist()
        assert (td.get(("next", "goal_distance"))[~done] >= 0).all()
        td = td_next
    env.close()
    assert len(finished) >= 8
    assert all(finished)


def test_lookup_rows_fills_only_the_flagged_rows(store):
    ids = torch.tensor([[3], [5], [7]])
    frames = store.lookup_rows(ids, torch.tensor([[True], [False], [True]]))
    assert frames.shape == (3, *store.frames.shape[1:])
    assert torch.equal(frames[0], store.frames[3]) and torch.equal(frames[2], store.frames[7])
    assert not frames[1].any()
    with pytest.raises(ValueError, match="demo_id"):
        store.lookup_rows(torch.tensor([[3], [25]]), torch.tensor([True, True]))
    with pytest.raises(ValueError, match="where must hold one flag per demo_id row"):
        store.lookup_rows(ids, torch.tensor([True, False]))


def test_spf_collection_with_init_only_lookup_matches_full_lookup(store, store_root):
    """The SPF policy encodes the memory where is_init is true only: looking frames up there only changes nothing."""
    torch.manual_seed(0)
    spf = make_spf_policy(SPFConfig(demo_length=5, sparsity=0.4, feature_dim=8, hidden_size=8, image_size=(32, 32))).eval()
    actor = make_actor(spf, 3)
    batches = {}
    for name, lookup in (("full", store.lookup_module()), ("init_only", store.lookup_module(only_where="is_init"))):
        policy = TensorDictSequential(lookup, actor, selected_out_keys=list(actor.out_keys))
        env = make_path_follow_env(demo_store=store_root, emit_demo_frames=False, num_agents=2, **ENV_KWARGS)
        env.append_transform(spf.make_tensordict_primer())
        env.set_seed(0)
        torch.manual_seed(1)  # the actor samples its actions: the same draws in both runs
        collector = Collector(env, policy, frames_per_batch=24, total_frames=24, auto_register_policy_transforms=False)
        try:
            batches[name] = next(iter(collector))
        finally:
            collector.shutdown()
    full, init_only = batches["full"], batches["init_only"]
    assert full["is_init"].sum() > 2  # episodes of max_steps=3: several resets inside the batch
    torch.testing.assert_close(init_only["logits"], full["logits"])
    torch.testing.assert_close(init_only["next", "memory_features"], full["next", "memory_features"])
    assert torch.equal(init_only["demo_id"], full["demo_id"])


def test_unrendered_env_may_leave_out_the_blank_frames():
    """Without rendering, the frames are blank: ``emit_demo_frames=False`` needs no store and
    plays the same episodes, rewards and expert labels."""
    from envs.scripted import ExpertPolicy

    def rollout(emit: bool):
        env = make_path_follow_env(render=False, emit_demo_frames=emit, with_expert=True, num_agents=2, **ENV_KWARGS)
        env.set_seed(3)
        return env, env.rollout(6, ExpertPolicy(), break_when_any_done=False)

    lean_env, lean = rollout(False)
    full_env, full = rollout(True)
    assert "demo_frames" not in lean.keys() and "demo_frames" not in lean_env.observation_spec.keys()
    assert not full["demo_frames"].any()
    assert (lean == full.exclude("demo_frames", ("next", "demo_frames"))).all()

"""Tests for spf_rl.modules.policy: SPF policy, baselines, TorchRL integration."""
from __future__ import annotations

import dataclasses

import pytest
import torch
import torch.nn.functional as F
from conftest import CountingEncoder
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import Bounded, Categorical, Composite
from torchrl.envs import Compose, EnvBase, InitTracker, SerialEnv, TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type, step_mdp
from torchrl.modules import set_recurrent_mode
from torchrl.modules.utils import get_primers_from_module

from spf_rl.modules import (
    ImageEncoder,
    OpenLoopPolicy,
    SPFConfig,
    SPFPolicy,
    make_action_only_policy,
    make_actor,
    make_rpf_policy,
    make_spf_policy,
)

H = W = 16
N = 6
CFG = SPFConfig(demo_length=N, sparsity=0.5, k=2, feature_dim=16, hidden_size=16, image_size=(H, W))
FACTORIES = {
    "spf": make_spf_policy,
    "rpf": make_rpf_policy,
    "action_only": make_action_only_policy,
}


# --------------------------------------------------------------------- helpers

class DemoEnv(EnvBase):
    """Tiny unbatched env emitting the SPF contract keys with random content."""

    def __init__(self, max_steps: int = 4, n: int = N, num_actions: int = 3, seed: int = 0):
        super().__init__()
        self.max_steps, self.n = max_steps, n
        self.observation_spec = Composite(
            pixels=Bounded(0, 255, shape=(H, W, 3), dtype=torch.uint8),
            demo_frames=Bounded(0, 255, shape=(n, H, W, 3), dtype=torch.uint8),
            demo_actions=Categorical(3, shape=(n,)),
        )
        self.action_spec = Categorical(num_actions)
        self.reward_spec = Bounded(-1, 1, shape=(1,))
        self.done_spec = Composite(
            {k: Categorical(2, shape=(1,), dtype=torch.bool) for k in ("done", "terminated", "truncated")}
        )
        self.rng = torch.Generator().manual_seed(seed)

    def _set_seed(self, seed):
        self.rng = torch.Generator().manual_seed(seed if seed is not None else 0)

    def _obs(self):
        return torch.randint(0, 256, (H, W, 3), dtype=torch.uint8, generator=self.rng)

    def _reset(self, td, **kwargs):
        self._t = 0
        self._demo = {
            "demo_frames": torch.randint(0, 256, (self.n, H, W, 3), dtype=torch.uint8, generator=self.rng),
            "demo_actions": torch.randint(0, 3, (self.n,), generator=self.rng),
        }
        false = torch.zeros(1, dtype=torch.bool)
        return TensorDict(pixels=self._obs(), **self._demo, done=false, terminated=false, truncated=false.clone())

    def _step(self, td):
        self._t += 1
        trunc = torch.tensor([self._t >= self.max_steps])
        return TensorDict(
            pixels=self._obs(),
            **self._demo,
            reward=torch.zeros(1),
            done=trunc,
            terminated=torch.zeros(1, dtype=torch.bool),
            truncated=trunc,
        )


def make_env():
    return TransformedEnv(DemoEnv(), InitTracker())


def _random_td(batch, n=N, init=True, seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        pixels=torch.randint(0, 256, (*batch, H, W, 3), dtype=torch.uint8, generator=g),
        demo_frames=torch.randint(0, 256, (*batch, n, H, W, 3), dtype=torch.uint8, generator=g),
        demo_actions=torch.randint(0, 3, (*batch, n), generator=g),
        is_init=torch.full((*batch, 1), init),
        batch_size=batch,
    )


def _make_trajectory(B=2, T=7, inits=((0, 4), (0, 2)), seed=0):
    """[B, T] observations with episode starts at the given steps (demo changes at each start)."""
    g = torch.Generator().manual_seed(seed)
    pixels = torch.randint(0, 256, (B, T, H, W, 3), dtype=torch.uint8, generator=g)
    is_init = torch.zeros(B, T, 1, dtype=torch.bool)
    demo_f = torch.empty(B, T, N, H, W, 3, dtype=torch.uint8)
    demo_a = torch.empty(B, T, N, dtype=torch.long)
    for b in range(B):
        for t in range(T):
            if t in inits[b]:
                is_init[b, t] = True
                f = torch.randint(0, 256, (N, H, W, 3), dtype=torch.uint8, generator=g)
                a = torch.randint(0, 3, (N,), generator=g)
            demo_f[b, t], demo_a[b, t] = f, a
    return TensorDict(pixels=pixels, demo_frames=demo_f, demo_actions=demo_a, is_init=is_init, batch_size=[B, T])


def _run_steps(policy, traj):
    """Step-by-step over [B, T], carrying the state like step_mdp + the primer (zeros at is_init)."""
    B, T = traj.shape
    state = {}
    inputs, logits = [], []
    for t in range(T):
        td = traj[:, t].clone()
        init = td["is_init"]
        for key, value in state.items():
            td.set(key, torch.where(init.reshape(B, *[1] * (value.ndim - 1)), torch.zeros_like(value), value))
        inputs.append(td.clone())
        out = policy(td)
        logits.append(out["logits"])
        state = {k: out["next", k] for k in out["next"].keys()}
    for key, value in inputs[1].items():  # the first step had no stored state: zeros
        if key not in inputs[0].keys():
            inputs[0].set(key, torch.zeros_like(value))
    return torch.stack(inputs, 1), torch.stack(logits, 1)


# --------------------------------------------------------------------- config / errors
@pytest.mark.parametrize("sparsity", [0, 1.5, -0.1])
def test_bad_sparsity(sparsity):
    with pytest.raises(ValueError, match=r"sparsity must be a number in the range \(0, 1\]"):
        SPFConfig(sparsity=sparsity)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"pointer_update": "linear"}, r"pointer_update must be one of \('paper', 'rpf'\)"),
        ({"memory_mode": "dense"}, r"memory_mode must be one of \('sparse', 'full', 'none'\)"),
        ({"num_actions": 5}, "num_actions must be one of"),
        ({"k": -1}, "k must be"),
        ({"image_size": (16,)}, "image_size"),
    ],
)
def test_bad_config(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SPFConfig(**kwargs)


def test_memory_modes_lengths():
    cfg = SPFConfig()
    assert cfg.memory_length == 24  # the default sparsity 0.8 of n = 30
    assert make_rpf_policy(dataclasses.replace(cfg, feature_dim=8, hidden_size=8)).memory_length == 30
    policy = make_action_only_policy(dataclasses.replace(cfg, feature_dim=8, hidden_size=8))
    assert policy.memory_length == 0 and "memory_features" not in policy.in_keys
    assert "demo_frames" not in policy.in_keys


def test_wrong_frame_shape_raises():
    policy = SPFPolicy(CFG)
    td = _random_td([2])
    td["pixels"] = torch.zeros(2, 32, 32, 3, dtype=torch.uint8)
    with pytest.raises(ValueError, match=r"pixels must have shape \[\*, 16, 16, 3\]"):
        policy(td)
    td = _random_td([2])
    td["demo_frames"] = torch.zeros(2, N, 1, H, W, dtype=torch.uint8)
    with pytest.raises(ValueError, match="demo_frames must have shape"):
        policy(td)


def test_demo_shorter_than_n_raises():
    policy = SPFPolicy(CFG)
    with pytest.raises(ValueError, match="demo_length"):
        policy(_random_td([2], n=N - 2))
    td = _random_td([2])
    td["demo_frames"] = td["demo_frames"][:, : N - 1]
    with pytest.raises(ValueError, match="demo_frames"):
        policy(td)


def test_demo_action_out_of_range_raises():
    td = _random_td([2])
    td["demo_actions"][0, 0] = 3
    with pytest.raises(ValueError, match=r"range\(num_actions=3\)"):
        SPFPolicy(CFG)(td)


# --------------------------------------------------------------------- step mode
@pytest.mark.parametrize("name", list(FACTORIES))
@pytest.mark.parametrize("batch", [[], [3], [2, 2]])
def test_step_shapes(name, batch):
    policy = FACTORIES[name](CFG)
    out = policy(_random_td(batch))
    assert out["logits"].shape == (*batch, 3)
    assert out["features"].shape == (*batch, 16)
    assert out["eta_used"].shape == (*batch, 1)
    assert out["next", "spf_hidden"].shape == (*batch, 16)
    assert out["next", "eta"].shape == (*batch, 1)
    if name == "action_only":
        assert ("next", "memory_features") not in out.keys(True)
    else:
        assert out["next", "memory_features"].shape == (*batch, policy.memory_length, 16)


def test_pointer_update_paper_and_rpf():
    for rule in ("paper", "rpf"):
        policy = SPFPolicy(dataclasses.replace(CFG, pointer_update=rule))
        with torch.no_grad():
            policy.cell.pointer_head.weight.zero_()
            policy.cell.pointer_head.bias.fill_(0.5)
        td = _random_td([3], init=False)
        td["eta"] = torch.tensor([[0.0], [2.25], [N - 1.2]])
        td["spf_hidden"] = torch.zeros(3, 16)
        out = policy(td)
        torch.testing.assert_close(out["eta_used"], td["eta"])
        step = torch.tanh(torch.tensor(0.5))
        if rule == "paper":
            expected = td["eta"] + step
        else:  # min(eta + 1 + tanh(b), n - 1): last row is clipped
            expected = torch.tensor([[1 + step], [3.25 + step], [N - 1.0]])
        torch.testing.assert_close(out["next", "eta"], expected)
    # negative increments move the paper pointer backwards, rpf still advances
    policy = SPFPolicy(CFG)
    assert torch.allclose(policy.update_pointer(torch.tensor([[2.0]]), torch.tensor([[-1e3]])), torch.tensor([[1.0]]))
    policy = SPFPolicy(dataclasses.replace(CFG, pointer_update="rpf"))
    assert torch.allclose(policy.update_pointer(torch.tensor([[2.0]]), torch.tensor([[-1e3]])), torch.tensor([[2.0]]))


def test_is_init_resets_state():
    torch.manual_seed(0)
    policy = SPFPolicy(CFG)
    td = _random_td([2], init=True)
    fresh = policy(td.clone())
    stale = td.clone()
    stale["spf_hidden"] = torch.randn(2, 16)
    stale["eta"] = torch.full((2, 1), 3.7)
    stale["memory_features"] = torch.randn(2, policy.memory_length, 16)
    out = policy(stale)
    torch.testing.assert_close(out["logits"], fresh["logits"])
    assert (out["eta_used"] == 0).all()
    # not init: the stored state is used (different logits, eta_used = stored)
    stale["is_init"][:] = False
    out2 = policy(stale.clone())
    torch.testing.assert_close(out2["eta_used"], torch.full((2, 1), 3.7))
    assert not torch.allclose(out2["logits"], fresh["logits"])


def test_memory_encoded_once_per_episode():
    enc = CountingEncoder(ImageEncoder(16, (H, W)))
    policy = SPFPolicy(CFG, encoder=enc)
    l = policy.memory_length
    B = 4
    td = _random_td([B], init=True)
    out = policy(td)
    assert enc.frames == B + B * l
    memory = out["next", "memory_features"]
    torch.testing.assert_close(memory, enc.inner(td["demo_frames"][:, policy.memory.indices]))
    # later steps of the episode: no memory frame is encoded, the stored memory is carried
    nxt = step_mdp(out)
    nxt["pixels"] = td["pixels"]
    nxt["is_init"] = torch.zeros(B, 1, dtype=torch.bool)
    for _ in range(3):
        enc.frames = 0
        out = policy(nxt)
        assert enc.frames == B
        torch.testing.assert_close(out["next", "memory_features"], memory)
        nxt = step_mdp(out)
        nxt["is_init"] = torch.zeros(B, 1, dtype=torch.bool)
    # two rows start a new episode: only their memory is encoded
    nxt["is_init"] = torch.tensor([[True], [False], [True], [False]])
    enc.frames = 0
    policy(nxt)
    assert enc.frames == B + 2 * l


# --------------------------------------------------------------------- sequence mode
@pytest.mark.parametrize("name", list(FACTORIES))
@pytest.mark.parametrize("pointer_update", ["paper", "rpf"])
def test_sequence_matches_steps(name, pointer_update):
    torch.manual_seed(0)
    policy = FACTORIES[name](dataclasses.replace(CFG, pointer_update=pointer_update))
    traj = _make_trajectory()
    with torch.no_grad():
        inputs, step_logits = _run_steps(policy, traj)
        # full sequence with an episode boundary mid-row
        with set_recurrent_mode(True):
            seq = policy(inputs.clone())
        torch.testing.assert_close(seq["logits"], step_logits, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(seq["eta_used"], inputs["eta"], rtol=1e-5, atol=1e-5)
        # without any stored state keys: zeros at the starts, same logits
        with set_recurrent_mode(True):
            bare = policy(traj.clone())
        torch.testing.assert_close(bare["logits"], step_logits, rtol=1e-5, atol=1e-5)
        # a window that starts mid-episode (t=0 not init) uses the stored state
        with set_recurrent_mode(True):
            part = policy(inputs[:, 1:].clone())
        torch.testing.assert_close(part["logits"], step_logits[:, 1:], rtol=1e-5, atol=1e-5)
        # 1-d input [T] and 3-d input [A, B, T]
        with set_recurrent_mode(True):
            one = policy(inputs[0].clone())
            three = policy(inputs.unsqueeze(0).expand(2, *inputs.shape).clone())
        torch.testing.assert_close(one["logits"], step_logits[0], rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(three["logits"][1], step_logits, rtol=1e-5, atol=1e-5)


def test_sequence_expanded_demo_view():
    """demo_frames given as an expanded [B, T, n, ...] view (one demo per row)."""
    torch.manual_seed(0)
    policy = SPFPolicy(CFG)
    traj = _make_trajectory(inits=((0,), (0,)))
    view = traj["demo_frames"][:, :1].expand(-1, traj.shape[1], -1, -1, -1, -1)
    assert view.stride(1) == 0
    with torch.no_grad():
        _, step_logits = _run_steps(policy, traj)
        td = traj.clone()
        td.set("demo_frames", view)
        with set_recurrent_mode(True):
            seq = policy(td)
    torch.testing.assert_close(seq["logits"], step_logits, rtol=1e-5, atol=1e-5)


def test_sequence_memory_encodes_at_starts_only():
    enc = CountingEncoder(ImageEncoder(16, (H, W)))
    policy = SPFPolicy(CFG, encoder=enc)
    traj = _make_trajectory()  # starts: row 0 at t=0, 4; row 1 at t=0, 2
    with torch.no_grad(), set_recurrent_mode(True):
        policy(traj)
    assert enc.frames == 2 * 7 + 4 * policy.memory_length


# --------------------------------------------------------------------- training
@pytest.mark.parametrize("name", list(FACTORIES))
def test_gradients_reach_every_parameter(name):
    torch.manual_seed(0)
    policy = FACTORIES[name](CFG)
    assert policy.attention.attention.soft_action_memory == (name == "action_only")
    traj = _make_trajectory(inits=((0,), (0,)), T=4)
    with set_recurrent_mode(True):
        out = policy(traj)
    target = torch.randint(0, 3, (2, 4))
    F.cross_entropy(out["logits"].reshape(-1, 3), target.reshape(-1)).backward()
    no_grad = [n for n, p in policy.named_parameters() if p.grad is None or p.grad.abs().sum() == 0]
    # action_only: the pointer head learns through the soft action memory
    assert no_grad == []


def test_action_only_without_soft_action_memory_has_no_pointer_gradient():
    """The hard window alone only sees floor(eta): why soft_action_memory defaults to True there."""
    torch.manual_seed(0)
    policy = make_action_only_policy(dataclasses.replace(CFG, soft_action_memory=False))
    assert not policy.attention.attention.soft_action_memory
    traj = _make_trajectory(inits=((0,), (0,)), T=4)
    with set_recurrent_mode(True):
        out = policy(traj)
    out["logits"].sum().backward()
    no_grad = [n for n, p in policy.named_parameters() if p.grad is None or p.grad.abs().sum() == 0]
    assert sorted(no_grad) == ["cell.pointer_head.bias", "cell.pointer_head.weight"]


def test_soft_action_memory_config():
    assert SPFConfig().use_soft_action_memory is False
    assert SPFConfig(memory_mode="none").use_soft_action_memory is True
    assert SPFConfig(memory_mode="none", soft_action_memory=False).use_soft_action_memory is False
    # None is kept, so replace() re-resolves it for the new memory mode
    assert make_action_only_policy(CFG).config.use_soft_action_memory is True
    assert make_rpf_policy(dataclasses.replace(CFG, memory_mode="none")).config.use_soft_action_memory is False
    # the flag works with visual memory too: psi takes D + window + C inputs
    policy = make_spf_policy(dataclasses.replace(CFG, soft_action_memory=True))
    assert policy.attention.attention.psi.in_features == 16 + 5 * 3 + 3
    assert policy(_random_td([2]))["logits"].shape == (2, 3)
    with pytest.raises(ValueError, match="soft_action_memory"):
        SPFConfig(soft_action_memory="yes")


def test_loss_falls_on_synthetic_data():
    torch.manual_seed(0)
    policy = SPFPolicy(CFG)
    B, T = 8, 5
    traj = _make_trajectory(B=B, T=T, inits=tuple((0,) for _ in range(B)))
    # target: a colour class painted into the frame (learnable through the encoder)
    classes = torch.randint(0, 3, (B, T))
    traj["pixels"][:] = 0
    for c in range(3):
        traj["pixels"][..., c, :, :][classes == c] = 255
    opt = torch.optim.Adam(policy.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        with set_recurrent_mode(True):
            out = policy(traj.clone())
        loss = F.cross_entropy(out["logits"].reshape(-1, 3), classes.reshape(-1))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.3 * losses[0], losses[::10]


# --------------------------------------------------------------------- TorchRL integration
def test_actor_primer_rollout_and_replay_in_sequence_mode():
    torch.manual_seed(0)
    policy = SPFPolicy(CFG)
    actor = make_actor(policy, 3)
    primer = get_primers_from_module(actor)  # the policy's and its parts' (the same keys)
    primers = list(primer) if isinstance(primer, Compose) else [primer]
    assert set().union(*(p.primers.keys() for p in primers)) == {"spf_hidden", "eta", "memory_features"}
    env = make_env().append_transform(primer)
    check_env_specs(env)
    with torch.no_grad():
        data = env.rollout(10, actor, break_when_any_done=False)
    assert data.shape == (10,)
    assert data["action"].dtype == torch.long and ((data["action"] >= 0) & (data["action"] < 3)).all()
    assert "action_log_prob" in data.keys()
    init = data["is_init"].squeeze(-1)
    assert init.tolist() == [True, False, False, False, True, False, False, False, True, False]
    assert (data["eta"][init] == 0).all() and (data["spf_hidden"][init] == 0).all()
    # step_mdp carried the state: root at t+1 == next at t inside an episode
    torch.testing.assert_close(data["eta"][1:4], data["next", "eta"][0:3])
    torch.testing.assert_close(data["memory_features"][1:4], data["next", "memory_features"][0:3])
    # the same trajectory in sequence mode gives the same logits and log-probs
    with torch.no_grad(), set_recurrent_mode(True):
        replay = actor(data.clone().exclude("logits", "action_log_prob").unsqueeze(0))
        lp = actor.get_dist(data.clone().unsqueeze(0)).log_prob(data["action"].unsqueeze(0))
    torch.testing.assert_close(replay["logits"][0], data["logits"], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(lp[0], data["action_log_prob"], rtol=1e-5, atol=1e-5)


def test_deterministic_actor_is_greedy():
    policy = SPFPolicy(CFG)
    actor = make_actor(policy, 3)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        out = actor(_random_td([5]))
    assert (out["action"] == out["logits"].argmax(-1)).all()


def test_collector_serial_env_with_primers():
    torch.manual_seed(0)
    actor = make_actor(SPFPolicy(CFG), 3)
    env = SerialEnv(2, make_env)
    collector = Collector(
        env, actor, frames_per_batch=12, total_frames=24, auto_register_policy_transforms=True
    )
    try:
        batches = list(collector)
    finally:
        collector.shutdown()
    assert len(batches) == 2
    data = batches[0]
    assert data.shape == (2, 6)
    for key in ("logits", "action", "eta", "spf_hidden", "memory_features", "features", "eta_used"):
        assert key in data.keys(), key
    assert (data["eta"][data["is_init"].squeeze(-1)] == 0).all()
    assert data["memory_features"].shape == (2, 6, CFG.memory_length, CFG.feature_dim)


# --------------------------------------------------------------------- open loop
def test_open_loop_policy_replays_and_resets():
    policy = OpenLoopPolicy(3)
    env = make_env().append_transform(policy.make_tensordict_primer())
    with torch.no_grad():
        data = env.rollout(9, make_actor(policy, 3), break_when_any_done=False)
    demo = data["demo_actions"]
    steps = [0, 1, 2, 3, 0, 1, 2, 3, 0]
    expected = torch.stack([demo[t, s] for t, s in enumerate(steps)])
    assert data["action"].tolist() == expected.tolist()
    assert data["open_loop_step"].squeeze(-1).tolist() == steps
    assert (data["logits"].argmax(-1) == data["action"]).all()


def test_open_loop_after_demo():
    td = TensorDict(
        demo_actions=torch.tensor([[0, 2], [0, 2]]),
        is_init=torch.zeros(2, 1, dtype=torch.bool),
        open_loop_step=torch.tensor([[1], [5]]),
        batch_size=[2],
    )
    assert OpenLoopPolicy(3)(td.clone())["action"].tolist() == [2, 1]  # turn left after the demo
    assert OpenLoopPolicy(4)(td.clone())["action"].tolist() == [2, 3]  # STOP when available
    with pytest.raises(ValueError, match="action_after_demo"):
        OpenLoopPolicy(3, action_after_demo=3)


if __name__ == "__main__":
    pytest.main([__file__, "--capture", "no", "--exitfirst"])


def test_initial_pointer_step_sets_the_untrained_increment():
    import math

    import pytest as _pytest

    from spf_rl.modules.policy import SPFConfig as _Config
    from spf_rl.modules.policy import SPFPolicy as _Policy

    policy = _Policy(_Config(demo_length=6, feature_dim=8, hidden_size=8, image_size=(16, 16), initial_pointer_step=0.9))
    hidden = torch.randn(4, 8)
    b = policy.cell.pointer_head(hidden)
    assert torch.allclose(torch.tanh(b), torch.full_like(b, 0.9), atol=1e-6)
    eta = policy.update_pointer(torch.zeros(4, 1), b)
    assert torch.allclose(eta, torch.full_like(eta, 0.9), atol=1e-6)
    assert math.isclose(policy.cell.pointer_head.bias.item(), math.atanh(0.9), rel_tol=1e-6)
    with _pytest.raises(ValueError, match="initial_pointer_step must be in"):
        _Config(initial_pointer_step=1.0)

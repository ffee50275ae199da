"""Tests for the recipes' configuration loading (YAML + preset + key=value overrides)."""
from __future__ import annotations

import dataclasses
import json
import re
import runpy
import sys
from pathlib import Path

import pytest

from spf_rl.config import load_config
from spf_rl.train.bc import BCConfig

RECIPES = Path(__file__).resolve().parents[1] / "recipes"


def test_default_and_quick_presets_load():
    default = load_config(BCConfig, "bc", [])
    assert default.model.name == "spf" and default.model.sparsity == 0.8
    assert default.test.episodes.split == "test" and default.test.num_episodes == 500
    quick = load_config(BCConfig, "bc", [], preset="bc_quick")
    assert quick.data.num_episodes < default.data.num_episodes
    assert quick.output_dir.startswith("runs/bc_quick/spf-s0.8")


def test_shorthands_and_dotted_overrides():
    config = load_config(BCConfig, "bc", ["model=rpf", "noise=locobot", "optim.epochs=3", "sparsity=0.4"])
    assert config.model.name == "rpf" and config.model.sparsity == 0.4
    assert config.data.episodes.noise == config.val.episodes.noise == config.test.episodes.noise == "locobot"
    assert config.optim.epochs == 3
    assert config.output_dir == "runs/bc/rpf-s0.4-seed0"


@pytest.mark.parametrize(
    "override, match",
    [("modle.name=spf", "modle"), ("model=transformer", "model name must be one of"), ("epochs", "key=value"), ("optim.epochs=many", "epochs")],
)
def test_bad_overrides_are_refused(override, match):
    with pytest.raises(ValueError, match=match):
        load_config(BCConfig, "bc", [override])


@pytest.mark.parametrize(
    "override, match",
    [
        ("noise=lol", r"noise must be one of \['locobot', 'none', 'paper', 'paper_symmetric', 'paper_unclipped'\]"),
        ("test.split=dev", r"split must be one of \['test', 'train', 'val'\]"),
        ("val.num_agents=0", "num_agents must be a positive int"),
    ],
)
def test_bad_values_are_refused_before_any_work(override, match, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["bc.py", override])
    with pytest.raises(SystemExit) as exit_info:
        runpy.run_path(str(RECIPES / "bc.py"), run_name="__main__")
    assert exit_info.value.code == 2
    assert re.fullmatch(f"bc.py: error: invalid configuration: {match}.*\n", capsys.readouterr().err)
    assert list(tmp_path.iterdir()) == []  # no dataset, no run directory


def test_long_preset_is_at_least_20k_steps_on_8k_episodes():
    config = load_config(BCConfig, "bc", [], preset="bc_long")
    steps = config.optim.epochs * (config.data.num_episodes // config.optim.batch_size)
    assert config.data.num_episodes >= 8000 and steps >= 20_000
    assert config.val.num_episodes >= 300  # checkpoints picked on at least 300 validation episodes
    assert config.output_dir.startswith("runs/bc_long/")


def test_pointer_rule_long_presets_chain_bc_into_dagger():
    """bc_pointer_long is bc_long with RPF's pointer rule; dagger_pointer_long starts from its best checkpoint."""
    from spf_rl.train.dagger import DAggerConfig

    bc = load_config(BCConfig, "bc", ["seed=1"], preset="bc_pointer_long")
    long = load_config(BCConfig, "bc", ["seed=1"], preset="bc_long")
    assert (bc.model.name, bc.model.sparsity, bc.model.pointer_update) == ("spf", 0.8, "rpf")
    assert long.model.pointer_update != "rpf"
    assert (bc.data, bc.optim, bc.val, bc.test) == (long.data, long.optim, long.val, long.test)  # the long schedule
    dagger = load_config(DAggerConfig, "dagger", ["seed=1"], preset="dagger_pointer_long")
    assert dagger.checkpoint == f"{bc.output_dir}/best.pt"
    assert dagger.bc_data.num_episodes == bc.data.num_episodes
    assert dagger.output_dir != load_config(DAggerConfig, "dagger", ["seed=1"], preset="dagger_long").output_dir


@pytest.mark.parametrize("preset", [None, "dagger_quick", "dagger_control", "dagger_pointer_long"])
def test_dagger_validates_on_episodes_its_start_was_not_picked_on(preset):
    """The BC run picked DAgger's start on the val split at BC's val seed; DAgger scores its rounds
    (round 0 included) on another seed's episodes, else round 0's selected maximum is favoured."""
    from spf_rl.train.dagger import DAggerConfig

    bc_val = load_config(BCConfig, "bc", [], preset="bc_long").val
    assert bc_val.episodes.seed == BCConfig().val.episodes.seed
    dagger = load_config(DAggerConfig, "dagger", [], preset=preset)
    assert dagger.val.episodes.split == bc_val.episodes.split and dagger.val.episodes.seed != bc_val.episodes.seed
    assert dagger.val.episodes.seed == DAggerConfig().val.episodes.seed
    if preset == "dagger_pointer_long":
        assert dagger.val.num_episodes == bc_val.num_episodes


@pytest.mark.parametrize("preset", ["dagger_long", "dagger_rpf", "dagger_rpf_original", "dagger_spf_rpf_pointer"])
def test_finished_dagger_rows_keep_the_validation_they_ran_with(preset):
    """Table 1's finished DAgger rows were validated on BC's val episodes; their presets still say so."""
    from spf_rl.train.bc import default_val_config
    from spf_rl.train.dagger import DAggerConfig

    assert load_config(DAggerConfig, "dagger", [], preset=preset).val == default_val_config()


def test_the_recipe_trains_the_dataclass_defaults():
    """One home for every default: bc.yaml only names the run."""
    from dataclasses import asdict

    recipe, library = asdict(load_config(BCConfig, "bc", [])), asdict(BCConfig())
    recipe.pop("output_dir"), library.pop("output_dir")
    assert recipe == library
    assert library["model"]["sparsity"] == 0.8 and library["model"]["initial_pointer_step"] == 0.9


def test_a_preset_builds_on_its_base(tmp_path, monkeypatch):
    from spf_rl import config as config_module

    (tmp_path / "bc.yaml").write_text("output_dir: runs/x\n")
    (tmp_path / "parent.yaml").write_text("optim:\n  epochs: 7\ndata:\n  num_episodes: 64\n")
    (tmp_path / "child.yaml").write_text("base: parent\ndata:\n  num_episodes: 32\n")
    (tmp_path / "loop_a.yaml").write_text("base: loop_b\n")
    (tmp_path / "loop_b.yaml").write_text("base: loop_a\n")
    monkeypatch.setattr(config_module, "CONFIG_DIR", tmp_path)
    child = load_config(BCConfig, "bc", [], preset="child")
    assert child.optim.epochs == 7 and child.data.num_episodes == 32  # the child's keys win over its base's
    with pytest.raises(ValueError, match="cycle"):
        load_config(BCConfig, "bc", [], preset="loop_a")
    with pytest.raises(ValueError, match="no file"):
        load_config(BCConfig, "bc", [], preset="nowhere")


def test_main_job_benchmark_compares_the_previous_and_current_budgets(tmp_path):
    import bench_main_job

    out = tmp_path / "main_job.json"
    report = bench_main_job.main(["--quick", "--output", str(out), "--workdir", str(tmp_path / "work")])
    assert json.loads(out.read_text()) == json.loads(json.dumps(report))
    previous, current = report["jobs"]["previous"], report["jobs"]["current"]
    assert (previous["epochs"], current["epochs"]) == (6, BCConfig().optim.epochs)
    assert report["gradient_step_ratio"] == current["gradient_steps"] / previous["gradient_steps"] == 2.0
    assert report["wall_ratio_current_to_previous"] == current["wall_seconds"] / previous["wall_seconds"] > 0
    assert previous["validation_episodes"] == 6 * 4  # every epoch, 4 episodes (quick)
    assert current["validation_episodes"] == 4 * 4  # epochs 3, 6, 9 and 12


def test_main_job_benchmark_against_a_baseline_runs_both_trees_and_pairs_their_test_episodes(tmp_path, monkeypatch):
    """--baseline runs each tree's recipes/bc.py in a child process (here the working tree stands in for the
    baseline's worktree) and pairs the two jobs' test episodes."""
    import contextlib

    import bench_main_job

    @contextlib.contextmanager
    def this_tree(repo, sha, path):
        yield bench_main_job.ROOT

    monkeypatch.setattr(bench_main_job, "baseline_worktree", this_tree)
    out = tmp_path / "main_job_baseline.json"
    report = bench_main_job.main(["--baseline", "HEAD", "--quick", "--output", str(out), "--workdir", str(tmp_path / "work")])
    assert json.loads(out.read_text()) == json.loads(json.dumps(report))
    baseline, current = report["jobs"]["baseline"], report["jobs"]["current"]
    assert report["speedup_current_over_baseline"] == baseline["wall_seconds"] / current["wall_seconds"] > 0
    success = report["paired_current_minus_baseline"]["metrics"]["success"]
    assert (success["a"], success["b"]) == (current["test_success"], baseline["test_success"])
    # the same code, seed and episodes on both sides: the same scores
    assert success["difference"] == 0.0 and current["test_spl"] == baseline["test_spl"]
    assert (tmp_path / "work" / "baseline" / "run" / "results.json").is_file()


def test_main_job_benchmark_refuses_an_unknown_baseline_before_any_work(tmp_path, capsys):
    import bench_main_job

    with pytest.raises(SystemExit) as exit_info:
        bench_main_job.main(["--baseline", "no-such-commit", "--workdir", str(tmp_path / "work")])
    assert exit_info.value.code == 2
    assert "--baseline" in capsys.readouterr().err and not (tmp_path / "work").exists()


@pytest.mark.parametrize("recipe", ["bc", "dagger"])
def test_every_documented_preset_is_accepted(recipe):
    """Each ``recipes/<recipe>.py --preset X`` in the README, docs/, recipes/ or a preset's own YAML is in the
    recipe's PRESETS and has a YAML."""
    import importlib
    import re

    root = Path(__file__).resolve().parents[1]
    texts = [
        root / "README.md", *sorted((root / "docs").glob("*.md")), *sorted((root / "recipes").glob("*.py")),
        *sorted((root / "recipes" / "configs").glob("*.yaml")),
    ]
    documented = {
        name
        for path in texts
        for name in re.findall(rf"recipes/{recipe}\.py[^`|\n]*?--preset (\w+)", path.read_text())
    }
    presets = importlib.import_module(recipe).PRESETS
    assert documented, f"no documented --preset for recipes/{recipe}.py"
    assert documented <= set(presets), f"documented but not accepted: {sorted(documented - set(presets))}"
    for name in presets:
        assert (root / "recipes" / "configs" / f"{name}.yaml").exists(), name


def test_pointer_routes_dagger_differs_from_routes_dagger_in_its_pointer_loss_alone():
    """dagger_routes_pointer is dagger_routes (the same start, data, rounds and episodes)
    with bc_routes_pointer's pointer loss; its output does not overwrite dagger_routes'."""
    from spf_rl.train.dagger import DAggerConfig

    bc = load_config(BCConfig, "bc", ["seed=1"], preset="bc_routes_pointer")
    plain = load_config(DAggerConfig, "dagger", ["seed=1"], preset="dagger_routes")
    dagger = load_config(DAggerConfig, "dagger", ["seed=1"], preset="dagger_routes_pointer")
    assert dagger.checkpoint == plain.checkpoint and dagger.bc_data == plain.bc_data == bc.data
    assert dagger.optim.pointer_coef == bc.optim.pointer_coef > 0 and plain.optim.pointer_coef == 0
    assert dagger.output_dir != plain.output_dir
    assert (dagger.env, dagger.val, dagger.test, dagger.rounds) == (plain.env, plain.val, plain.test, plain.rounds)
    assert dataclasses.replace(dagger.optim, pointer_coef=0.0) == plain.optim


def test_more_routes_dagger_continues_the_kept_weights_on_fresh_routes():
    """dagger_routes_pointer_more is dagger_routes_pointer from that run's shipped kept weights, into
    its own directory, and every one of its rounds draws another seed than every round of the first run."""
    from spf_rl.train.dagger import DAggerConfig, episode_seed_of_round

    first = load_config(DAggerConfig, "dagger", ["seed=2"], preset="dagger_routes_pointer")
    more = load_config(DAggerConfig, "dagger", ["seed=2"], preset="dagger_routes_pointer_more")
    assert more.checkpoint == "checkpoints/routes/dagger_pointer-spf_random-seed2.pt"
    assert Path(more.checkpoint).is_file() and more.output_dir not in (first.output_dir, first.checkpoint)
    assert dataclasses.replace(more, checkpoint=first.checkpoint, output_dir=first.output_dir, round_seed_offset=0) == first
    seeds = [{episode_seed_of_round(config, r) for r in range(1, config.rounds + 1)} for config in (first, more)]
    assert len(seeds[1]) == more.rounds and not seeds[0] & seeds[1]
    with pytest.raises(ValueError, match="round_seed_offset must be a non-negative int"):
        dataclasses.replace(first, round_seed_offset=-1)


def test_routes_dagger_starts_from_the_routes_bc_run_on_its_data_and_routes():
    """dagger_routes reuses bc_routes' dataset (the same DatasetConfig), starts from its best.pt,
    and collects, validates and tests on the same route mixture and lengths."""
    from spf_rl.train.dagger import DAggerConfig

    for seed in (0, 2):
        bc = load_config(BCConfig, "bc", [f"seed={seed}"], preset="bc_routes")
        dagger = load_config(DAggerConfig, "dagger", [f"seed={seed}"], preset="dagger_routes")
        assert dagger.bc_data == bc.data
        assert dagger.checkpoint == f"{bc.output_dir}/best.pt"
        env, data = dagger.env.episodes, bc.data.episodes
        assert (env.demo_length, env.max_steps, env.route_style, env.route_lengths) == (
            data.demo_length, data.max_steps, data.route_style, data.route_lengths
        )
        for evaluation in (dagger.val.episodes, dagger.test.episodes):  # sized as the collection episodes
            assert (evaluation.route_style, evaluation.route_lengths, evaluation.demo_length) == (
                data.route_style, data.route_lengths, 100
            )


def test_the_robust_route_preset_starts_from_routes_spf_and_repeats_in_changed_worlds():
    from spf_rl.hub import read_manifest
    from spf_rl.train.dagger import DAggerConfig

    robust = load_config(DAggerConfig, "dagger", ["seed=2"], preset="dagger_routes_robust")
    more = load_config(DAggerConfig, "dagger", ["seed=2"], preset="dagger_routes_pointer_more")
    assert robust.checkpoint == f"checkpoints/{read_manifest()['names']['routes-spf'].replace('seed0', 'seed2')}"
    assert robust.round_seed_offset > more.round_seed_offset and robust.output_dir != more.output_dir
    assert robust.optim == more.optim and robust.rounds == more.rounds and robust.bc_data == more.bc_data
    for episodes in (robust.env.episodes, robust.val.episodes):
        assert "light@1.0" in episodes.conditions and "none" in episodes.conditions and episodes.memory_mismatch == 0.2
        assert episodes.route_style == more.env.episodes.route_style and episodes.demo_length == 100
    assert robust.bc_data.episodes.conditions is None  # BC data stays the teaching world's


def test_the_anchor_preset_differs_from_the_robust_one_in_the_anchor_alone():
    from spf_rl.train.dagger import DAggerConfig

    robust = load_config(DAggerConfig, "dagger", ["seed=1"], preset="dagger_routes_robust")
    anchor = load_config(DAggerConfig, "dagger", ["seed=1"], preset="dagger_routes_robust_anchor")
    assert anchor.anchor_radius == 8 and robust.anchor_radius is None
    assert dataclasses.replace(anchor, anchor_radius=None, output_dir=robust.output_dir) == robust


def test_the_normalized_preset_differs_from_the_anchor_one_in_the_frames_alone():
    from spf_rl.train.dagger import DAggerConfig

    anchor = load_config(DAggerConfig, "dagger", ["seed=1"], preset="dagger_routes_robust_anchor")
    normalized = load_config(DAggerConfig, "dagger", ["seed=1"], preset="dagger_routes_robust_normalized")
    assert normalized.normalize_frames is True and anchor.normalize_frames is None and normalized.anchor_radius == 8
    assert dataclasses.replace(normalized, normalize_frames=None, output_dir=anchor.output_dir) == anchor
    with pytest.raises(ValueError, match="normalize_frames"):
        load_config(DAggerConfig, "dagger", ["normalize_frames=maybe"], preset="dagger_routes_robust_normalized")
    with pytest.raises(ValueError, match="normalize_frames must be true, false or None"):
        DAggerConfig(normalize_frames=2)


def test_the_share_preset_differs_from_the_normalized_one_in_the_rounds_share_alone():
    from spf_rl.train.dagger import DAggerConfig

    normalized = load_config(DAggerConfig, "dagger", ["seed=2"], preset="dagger_routes_robust_normalized")
    share = load_config(DAggerConfig, "dagger", ["seed=2"], preset="dagger_routes_robust_share")
    assert share.rounds_share == 0.5 and normalized.rounds_share is None
    assert share.output_dir == "runs/dagger_routes_robust_share/spf_random-seed2"
    assert dataclasses.replace(share, rounds_share=None, output_dir=normalized.output_dir) == normalized
    with pytest.raises(ValueError, match="rounds_share"):
        load_config(DAggerConfig, "dagger", ["rounds_share=2"], preset="dagger_routes_robust_share")


def test_the_gate_preset_differs_from_the_normalized_one_in_the_replay_gate_alone():
    from spf_rl.train.dagger import DAggerConfig

    normalized = load_config(DAggerConfig, "dagger", ["seed=1"], preset="dagger_routes_robust_normalized")
    gate = load_config(DAggerConfig, "dagger", ["seed=1"], preset="dagger_routes_robust_gate")
    assert gate.replay_gate is True and normalized.replay_gate is None
    assert gate.optim.replay_gate_coef == 0.5 and normalized.optim.replay_gate_coef == 0.0
    assert gate.output_dir == "runs/dagger_routes_robust_gate/spf_random-seed1"
    assert dataclasses.replace(gate, replay_gate=None, output_dir=normalized.output_dir,
                               optim=dataclasses.replace(gate.optim, replay_gate_coef=0.0)) == normalized
    with pytest.raises(ValueError, match="replay_gate"):
        load_config(DAggerConfig, "dagger", ["replay_gate=maybe"], preset="dagger_routes_robust_gate")
    with pytest.raises(ValueError, match="replay_gate must be true, false or None"):
        DAggerConfig(replay_gate=2)
    with pytest.raises(ValueError, match="optim.replay_gate_coef must be a finite number >= 0"):
        load_config(DAggerConfig, "dagger", ["optim.replay_gate_coef=-1"], preset="dagger_routes_robust_gate")
    with pytest.raises(ValueError, match="needs the replay gate: set replay_gate=true"):
        load_config(DAggerConfig, "dagger", ["replay_gate=false"], preset="dagger_routes_robust_gate")

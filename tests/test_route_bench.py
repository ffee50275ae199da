"""The route benchmark (spf_rl.eval.route_bench, recipes/route_bench.py): options, a tiny run, resuming."""
from __future__ import annotations

import json
import re

import pytest
import route_bench as recipe

from spf_rl import evaluation
from spf_rl.checkpoint import save_checkpoint
from spf_rl.eval import route_bench
from spf_rl.modules.policy import SPFConfig
from spf_rl.modules.registry import build_policy


def test_buckets_are_parsed_sorted_and_checked():
    assert route_bench.parse_buckets("61-100,10-30, 31-60") == ((10, 30), (31, 60), (61, 100))
    assert route_bench.parse_buckets("20") == ((20, 20),)
    for text, match in [("10-30,30-60", "overlap"), ("30-10", "lo <= hi"), ("10-101", "<= 100"), ("a-b", "is not lo-hi"),
                        ("", "no buckets")]:
        with pytest.raises(ValueError, match=f"argument --buckets: .*{match}"):
            route_bench.parse_buckets(text)


@pytest.mark.parametrize(
    ("kwargs", "option"),
    [
        ({"episodes": 0}, "--episodes"),
        ({"episodes": -3}, "--episodes"),
        ({"models": ("spf-s0.9",)}, "--models"),
        ({"models": ("missing/best.pt",)}, "--models"),
        ({"styles": ("zigzag",)}, "--styles"),
        ({"buckets": ((5, 30),)}, "--buckets"),
        ({"sets": ("val",)}, "--sets"),
        ({"noise": "loud"}, "--noise"),
        ({"seed": -1}, "--seed"),
        ({"num_resamples": 0}, "--num-resamples"),
        ({"random_sparsity": 1.5}, "--random-sparsity"),
        ({"num_collectors": 0}, "--num-collectors"),
        ({"reference": "spf-s0.6"}, "--reference"),
        ({"reference": "open_loop"}, "--reference"),
    ],
)
def test_bad_options_are_refused_naming_the_option(kwargs, option):
    with pytest.raises(ValueError, match=f"argument {option}:"):
        route_bench.BenchOptions(**{"models": ("spf-s0.8",), **kwargs})


def test_defaults_leave_out_homing_and_ppo_and_quick_is_small():
    models = route_bench.BenchOptions().models
    assert "spf-s0.8" in models and "lengths-spf-s0.8" in models and "spf_random-s0.2-1" in models
    assert not any(m.startswith(("homing-", "ppo-")) for m in models)
    quick = route_bench.BenchOptions(quick=True)
    assert (quick.models, quick.episodes, quick.sets, quick.buckets) == (route_bench.QUICK_MODELS, 8, ("test",), ((10, 30), (31, 60)))
    assert route_bench.BenchOptions(models=("ppo-spf-s0.8",)).models == ("ppo-spf-s0.8",)  # named: allowed


@pytest.mark.parametrize("argv", [["--episodes", "0"], ["--models", "nope"], ["--buckets", "10-5"], ["--styles", "walk"],
                                  ["--models", "spf-s0.8", "--reference", "rpf_original-s1"]])
def test_the_recipe_refuses_bad_arguments_before_any_work(argv, capsys, monkeypatch):
    monkeypatch.setattr(route_bench, "run_bench", lambda *args: pytest.fail("ran"))
    with pytest.raises(SystemExit) as info:
        recipe.main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert re.fullmatch(r"\S+: error: argument --[^\n]*\n", err), err  # the message alone, one line


def test_the_recipe_refuses_a_model_of_another_frame_size_before_any_work(tmp_path, capsys, monkeypatch):
    config = SPFConfig(demo_length=10, feature_dim=8, hidden_size=8, image_size=(16, 16))
    checkpoint = tmp_path / "tiny" / "best.pt"
    checkpoint.parent.mkdir()
    save_checkpoint(checkpoint, "spf", config, {"model": build_policy("spf", config).state_dict()})
    monkeypatch.setattr(route_bench, "run_bench", lambda *args: pytest.fail("ran"))
    with pytest.raises(SystemExit) as info:
        recipe.main(["--models", str(checkpoint), "--out", str(tmp_path / "bench.json")])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert re.fullmatch(r"\S+: error: argument --models: [^\n]*sees \(16, 16\) frames[^\n]*\n", err), err
    assert not (tmp_path / "bench.json").exists()


def test_a_tiny_run_pairs_models_by_episode_and_resumes(tmp_path, monkeypatch):
    config = SPFConfig(demo_length=10, feature_dim=8, hidden_size=8, image_size=(16, 16))
    checkpoint = tmp_path / "tiny" / "best.pt"
    checkpoint.parent.mkdir()
    save_checkpoint(checkpoint, "spf", config, {"model": build_policy("spf", config).state_dict()})
    out = tmp_path / "bench.json"
    options = route_bench.BenchOptions(
        models=(str(checkpoint),), styles=("driven",), buckets=((10, 12),), sets=("test",), episodes=2, test_houses=2,
        image_size=16, num_resamples=200, out=out, store_root=str(tmp_path / "stores"),
    )
    content = route_bench.run_bench(options)

    saved = json.loads(out.read_text())
    assert list(saved["cells"]) == ["test/driven/10-12"]
    assert saved["setup"]["episodes"] == 2 and saved["setup"]["sets"] == {"test": 2} and saved["setup"]["seed"] == 2
    assert list(saved["setup"]["models"]) == ["open_loop", "tiny/best"]
    cell = saved["cells"]["test/driven/10-12"]
    assert cell["key"]["episodes"]["route_lengths"] == [10, 12] and cell["key"]["episodes"]["demo_length"] == 12
    assert len(cell["episodes"]["episode_seed"]) == 2 and len(set(cell["episodes"]["house_seed"])) <= 2
    for label in ("open_loop", "tiny/best"):
        records = cell["models"][label]["columns"]
        assert all(len(records[key]) == 2 for key in route_bench.BENCH_RECORD_FIELDS)
        stats = cell["stats"][label]
        assert set(route_bench.BENCH_METRICS) <= set(stats) and stats["episodes"] == 2
    assert set(cell["stats"]["tiny/best"]["vs_open_loop"]) == {"success", "ndtw"}
    floor = cell["models"]["open_loop"]["columns"]
    same = route_bench.paired_against(floor, floor, cell["episodes"]["house_seed"], num_resamples=200)
    assert same["success"]["difference"] == 0.0 and same["ndtw"]["difference"] == 0.0
    assert "| test | driven | 10-12 |" in content["table"] and (tmp_path / "bench.png").is_file()
    assert (tmp_path / "bench.md").read_text().strip() == content["table"] + "\n\n" + content["table_by_model"]
    by_model = content["table_by_model"].splitlines()
    assert by_model[2] == "| model | driven 10-12 | driven |" and any(line.startswith("| tiny/best | ") for line in by_model)
    for label in ("open_loop", "tiny/best"):  # one cell per style here: the style's mean is the cell's
        assert content["by_style"]["test"]["driven"][label]["success"] == pytest.approx(cell["stats"][label]["success"]["mean"])

    # a rerun of the same set-up evaluates nothing; one more model plays only itself, on the same episodes
    played = []

    def fail(policy, config, progress=False):
        raise AssertionError("a finished cell was evaluated again")

    monkeypatch.setattr(evaluation, "evaluate_policy", fail)
    again = route_bench.run_bench(options)
    assert again["cells"]["test/driven/10-12"]["models"] == cell["models"]

    monkeypatch.undo()
    real = evaluation.evaluate_policy

    def counting(policy, config, progress=False):
        played.append(type(policy).__name__)
        return real(policy, config, progress)

    monkeypatch.setattr(evaluation, "evaluate_policy", counting)
    twin = tmp_path / "twin" / "best.pt"
    twin.parent.mkdir()
    twin.write_bytes(checkpoint.read_bytes())
    more = route_bench.run_bench(route_bench.BenchOptions(**{**_fields(options), "models": (str(checkpoint), str(twin))}))
    assert played == ["SPFPolicy"]
    cell = more["cells"]["test/driven/10-12"]
    assert cell["models"]["twin/best"]["columns"] == cell["models"]["tiny/best"]["columns"]  # same weights, same episodes
    assert cell["stats"]["twin/best"]["vs_open_loop"] == cell["stats"]["tiny/best"]["vs_open_loop"]


def _fields(options) -> dict:
    names = ("models", "styles", "buckets", "sets", "episodes", "seed", "noise", "out", "quick", "device", "random_sparsity",
             "num_resamples", "test_houses", "image_size", "num_agents", "num_collectors", "store_root", "progress")
    return {name: getattr(options, name) for name in names}


def test_training_seeds_of_one_recipe_are_pooled_into_one_column():
    rng = __import__("numpy").random.default_rng(0)
    houses = [h for h in range(4) for _ in range(8)]

    def records(p):
        success = (rng.random(32) < p).astype(float).tolist()
        return {"success": success, "spl": [0.5 * s for s in success], "ndtw": rng.random(32).tolist(), "sdtw": [0.0] * 32}

    models = {"open_loop": records(0.3), "r/a-seed0": records(0.9), "r/a-seed2": records(0.6), "r/a-seed1": records(0.8),
              "r/b-seed0": records(0.5)}
    cell = {"set": "test", "style": "tour", "bucket": [10, 30], "episodes": {"house_seed": houses},
            "models": {label: {"columns": rec} for label, rec in models.items()}}
    stats = route_bench.cell_stats(cell, num_resamples=500)

    assert route_bench.seed_groups(list(models)) == {"r/a (3 seeds)": ["r/a-seed0", "r/a-seed1", "r/a-seed2"]}
    pooled = stats["r/a (3 seeds)"]
    per_seed = [stats[f"r/a-seed{s}"] for s in range(3)]
    for metric in route_bench.BENCH_METRICS:
        means = [row[metric]["mean"] for row in per_seed]
        assert pooled["per_seed"][metric] == pytest.approx(means)
        assert pooled[metric]["mean"] == pytest.approx(sum(means) / 3)
        low, high = pooled[metric]["ci"]
        assert low <= pooled[metric]["mean"] <= high
    for metric in route_bench.BENCH_PAIRED_METRICS:
        differences = [row["vs_open_loop"][metric]["difference"] for row in per_seed]
        assert pooled["vs_open_loop"][metric]["difference"] == pytest.approx(sum(differences) / 3)

    setup = {"episodes": 32, "models": {label: {} for label in models}, "seed_groups": route_bench.seed_groups(list(models))}
    table = route_bench.format_table({"setup": setup, "cells": {"test/tour/10-30": {**cell, "stats": stats}}})
    header, _, row = table.splitlines()[:3]
    assert header.endswith("| r/b-seed0 | r/a (3 seeds) |")
    assert row.split(" | ")[-1].startswith(f"{pooled['success']['mean']:.2f}")
    assert "pooled over seeds" in table


def test_every_model_is_paired_with_the_reference_per_world():
    rng = __import__("numpy").random.default_rng(1)
    houses = [h for h in range(4) for _ in range(8)]

    def columns(p):
        return {"success": (rng.random(32) < p).astype(float).tolist(), "ndtw": rng.random(32).tolist()}

    cells = {}
    for world in (None, "light@1.0=1.0"):
        models = {"open_loop": columns(0.5), "old": columns(0.4), "new": columns(0.8)}
        cells[f"test/tour/10-30/{world}"] = {"set": "test", "world": world, "stats": {}, "episodes": {"house_seed": houses},
                                             "models": {label: {"columns": c} for label, c in models.items()}}
    setup = {"models": {"open_loop": {}, "old": {}, "new": {}}, "reference": "old"}
    worlds = route_bench.by_world({"setup": setup, "cells": cells}, num_resamples=300)["test"]
    assert set(worlds) == {"none", "light@1.0"}
    for world, cell in zip(("none", "light@1.0"), cells.values()):
        new, old = (cell["models"][m]["columns"]["success"] for m in ("new", "old"))
        paired = worlds[world]["new"]["vs_reference"]["success"]
        assert paired["difference"] == pytest.approx(sum(new) / 32 - sum(old) / 32)
        assert paired["ci"][0] <= paired["difference"] <= paired["ci"][1]
        assert "vs_reference" not in worlds[world]["old"] and "vs_reference" not in worlds[world]["open_loop"]
    table = route_bench.format_vs_reference({"test": worlds}, ["open_loop", "old", "new"], "old").splitlines()
    assert table[0] == "**test**: success minus old's" and table[2] == "| world | new |"
    difference = worlds["light@1.0"]["new"]["vs_reference"]["success"]["difference"]
    assert table[5].startswith(f"| light@1.0 | {difference:+.2f} [")
    # a seed group is never paired with one of its own seeds, nor a seed with its group
    grouped = {key: {**cell, "models": {"open_loop": cell["models"]["open_loop"], "r/m-seed0": cell["models"]["old"],
                                        "r/m-seed1": cell["models"]["new"], "other": cell["models"]["new"]}}
               for key, cell in cells.items()}
    labels = {"open_loop": {}, "r/m-seed0": {}, "r/m-seed1": {}, "other": {}}
    for reference, paired, unpaired in (("r/m-seed0", {"r/m-seed1", "other"}, {"r/m (2 seeds)"}),
                                        ("r/m (2 seeds)", {"other"}, {"r/m-seed0", "r/m-seed1"})):
        setup_g = {"models": labels, "seed_groups": {"r/m (2 seeds)": ["r/m-seed0", "r/m-seed1"]}, "reference": reference}
        rows = route_bench.by_world({"setup": setup_g, "cells": grouped}, num_resamples=100)["test"]["none"]
        assert {label for label, row in rows.items() if "vs_reference" in row} == paired
        assert not unpaired & {label for label, row in rows.items() if "vs_reference" in row}
    # without a reference the rows are as before
    plain = route_bench.by_world({"setup": {"models": setup["models"]}, "cells": cells}, num_resamples=300)["test"]
    assert not any("vs_reference" in row for rows in plain.values() for row in rows.values())

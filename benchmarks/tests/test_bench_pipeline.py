"""benchmarks/bench_pipeline.py: the baseline worktree, per-repeat ratios and their medians, the JSON and its
targets, bad options, and a tiny smoke run of every measure against the working tree (a smoke run, not a result)."""
from __future__ import annotations

import contextlib
import dataclasses
import json
import subprocess
from pathlib import Path

import bench_baseline
import bench_pipeline
import pytest

ROOT = Path(__file__).resolve().parents[2]


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True, text=True).stdout.strip()


@pytest.fixture()
def tiny_repo(tmp_path):
    """A git repository with two commits; returns (repo, first SHA, second SHA)."""
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    shas = []
    for text in ("one", "two"):
        (repo / "file.txt").write_text(text)
        _git(repo, "add", "file.txt")
        _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", text)
        shas.append(_git(repo, "rev-parse", "HEAD"))
    return repo, shas[0], shas[1]


def test_worktree_is_made_at_the_commit_reused_and_moved(tiny_repo, tmp_path):
    repo, first, second = tiny_repo
    path = tmp_path / "wt" / "baseline"
    assert bench_baseline.resolve_commit(first[:7], repo) == first
    assert bench_baseline.ensure_worktree(repo, first, path) is False  # made
    assert _git(path, "rev-parse", "HEAD") == first and (path / "file.txt").read_text() == "one"
    assert bench_baseline.ensure_worktree(repo, first, path) is True  # reused as it is
    (path / "file.txt").write_text("edited")  # a modified worktree is not reused
    assert bench_baseline.ensure_worktree(repo, first, path) is False
    assert (path / "file.txt").read_text() == "one"
    assert bench_baseline.ensure_worktree(repo, second, path) is False  # another commit: made again
    assert (path / "file.txt").read_text() == "two"
    plain = tmp_path / "plain"
    plain.mkdir()
    with pytest.raises(ValueError, match="not a git worktree"):
        bench_baseline.ensure_worktree(repo, first, plain)
    with bench_baseline.baseline_worktree(repo, first) as temporary:  # no path: a temporary one, removed after
        assert _git(temporary, "rev-parse", "HEAD") == first
    assert not temporary.exists()
    assert str(temporary) not in _git(repo, "worktree", "list")


def test_unknown_commit_is_refused(tiny_repo):
    repo, _, _ = tiny_repo
    with pytest.raises(ValueError, match="not a commit"):
        bench_baseline.resolve_commit("0123456789abcdef", repo)


def _output(values: dict[str, float], flops_per_s: float = 0.0, kernel_share: float = 0.5) -> dict:
    """A child's output with these measure values (canned): one second of training, of which
    the kernels replayed alone take ``kernel_share``."""
    measures = {name: {"value": value, "unit": bench_pipeline.UNITS[name]} for name, value in values.items()}
    if "training" in measures:
        measures["training"].update(
            flops_per_s=flops_per_s, seconds=1.0, kernel_flops=flops_per_s, kernel_seconds=kernel_share
        )
    return {"measures": measures, "torch_threads": 2, "spf_rl_file": str(ROOT / "spf_rl" / "__init__.py")}


def _repeat(raw: float, pipelines: float, matmul: float, training: float, flops: float, kernel_share: float = 0.5) -> dict:
    values = {"raw": raw, "matmul": matmul, "dataset_generation": pipelines, "dagger_collection": pipelines / 2,
              "evaluation": pipelines / 4, "training": training}
    return _output(values, flops_per_s=flops, kernel_share=kernel_share)


def test_ratios_are_taken_within_a_repeat_and_each_figure_is_the_median():
    # the machine slows down in repeat 2: the pipelines and their reference move together
    new = [_repeat(1000.0, 800.0, 100.0, 50.0, 40.0, 0.5), _repeat(500.0, 400.0, 50.0, 25.0, 20.0, 0.25),
           _repeat(1000.0, 900.0, 100.0, 60.0, 60.0, 0.8)]
    baseline = [_output({"training": value}) for value in (25.0, 20.0, 50.0)]
    summary = bench_pipeline.summarise(new, baseline)
    assert summary["ratios_to_raw"]["dataset_generation"] == pytest.approx(0.8)  # median of 0.8, 0.8, 0.9
    assert summary["ratios_to_raw"]["dagger_collection"] == pytest.approx(0.4)
    assert summary["ratios_to_raw"]["evaluation"] == pytest.approx(0.2)
    assert summary["raw_fps"] == 1000.0 and summary["matmul_flops"] == 100.0
    # the kernels' ceiling: the step's FLOPs over the kernels' seconds alone, / matmul (0.8, 1.6, 0.75)
    assert summary["training"] == {
        "labelled_steps_per_s": 50.0, "flops_per_s": 40.0, "fraction_of_matmul": 0.4,
        "kernel_fraction_of_matmul": pytest.approx(0.8), "kernel_share_of_step": 0.5,
    }
    assert summary["training_speedup"] == pytest.approx(1.25)  # median of 2.0, 1.25, 1.2
    assert summary["baseline_labelled_steps_per_s"] == 25.0
    assert summary["measures"]["raw"]["repeats"] == [1000.0, 500.0, 1000.0]
    holds = {name: target["holds"] for name, target in summary["targets"].items()}
    assert holds == {"dataset_generation": True, "dagger_collection": False, "evaluation": False,
                     "training_speedup": False, "fraction_of_matmul": False}


@contextlib.contextmanager
def _no_worktree(repo, sha, path=None):
    yield Path("/nonexistent-baseline")


def test_json_layout_from_canned_child_outputs(tmp_path, monkeypatch):
    new = [_repeat(1000.0, 900.0, 1e11, 300.0, 6e10) for _ in range(3)]
    baseline = [_output({"training": 200.0}) for _ in range(3)]
    seen = {}

    def fake_benchmark(args, baseline_tree, scratch):
        seen.update(tree=baseline_tree, sizes=args.sizes, repeats=args.repeats)
        return new, baseline

    monkeypatch.setattr(bench_pipeline, "baseline_worktree", _no_worktree)
    monkeypatch.setattr(bench_pipeline, "run_benchmark", fake_benchmark)
    out = tmp_path / "results" / "pipeline.json"
    result = bench_pipeline.main(["--quick", "--baseline", "HEAD", "--output", str(out)])
    written = json.loads(out.read_text())
    assert written == json.loads(json.dumps(result))
    assert not list(out.parent.glob(".*.tmp*"))  # written through a temporary file, renamed
    assert seen == {"tree": Path("/nonexistent-baseline"), "sizes": bench_pipeline.QUICK_SIZES, "repeats": 3}
    # the shape the issue asks for
    assert written["raw_fps"] == 1000.0 and written["matmul_flops"] == 1e11
    assert written["workers"] == 2 and written["quick"] is True
    assert set(written["ratios_to_raw"]) == {"dataset_generation", "dagger_collection", "evaluation"}
    assert written["ratios_to_raw"]["dataset_generation"] == pytest.approx(0.9)
    assert written["training"] == {
        "labelled_steps_per_s": 300.0, "flops_per_s": 6e10, "fraction_of_matmul": 0.6,
        "kernel_fraction_of_matmul": pytest.approx(1.2), "kernel_share_of_step": 0.5,
    }
    assert written["baseline"] == {"commit": _git(ROOT, "rev-parse", "HEAD"), "labelled_steps_per_s": 200.0}
    assert written["training_speedup"] == 1.5
    assert written["targets"]["training_speedup"] == {"target": 1.3, "measured": 1.5, "holds": True}
    assert written["setup"]["sizes"]["dataset_episodes"] == 128 and written["machine"]["cpu_count"] >= 1
    assert written["runs"] == {"new": new, "baseline": baseline}


#: Bad command lines; the option named first is the one the error must name.
BAD_COMMAND_LINES = ["--repeats 0", "--repeats 2", "--workers 0", "--baseline 0123456789abcdef0123"]


@pytest.mark.parametrize("line", BAD_COMMAND_LINES)
def test_bad_options_are_refused_before_any_work(line, monkeypatch, capsys):
    argv = line.split()

    def no_work(*args, **kwargs):
        raise AssertionError("work started despite a bad option")

    monkeypatch.setattr(bench_pipeline, "baseline_worktree", no_work)
    monkeypatch.setattr(bench_pipeline, "run_benchmark", no_work)
    with pytest.raises(SystemExit) as exit_info:
        bench_pipeline.main([*argv, "--output", "/nonexistent/never-written.json"])
    assert exit_info.value.code == 2
    assert argv[0] in capsys.readouterr().err


def test_the_worker_has_a_function_for_every_measure():
    import bench_pipeline_worker

    assert tuple(bench_pipeline_worker.MEASURE_FUNCTIONS) == bench_pipeline.MEASURES


def test_smoke_every_measure_runs_against_the_working_tree(tmp_path):
    """A tiny run of the child (the script the benchmark runs in each tree), here on the working tree only."""
    sizes = dataclasses.replace(
        bench_pipeline.Sizes(),
        dataset_episodes=4, dagger_episodes=2, num_agents=2, eval_episodes=2, eval_agents=2,
        train_steps=1, train_warmup_steps=1, raw_chunks=1, raw_chunk_frames=20,
        num_houses=1, demo_length=5, max_steps=6, image_size=32, workers=1,
    )
    output = bench_pipeline._child(bench_pipeline.MEASURES, sizes, tmp_path / "new", ROOT)
    assert output["spf_rl_file"] == str(ROOT / "spf_rl" / "__init__.py")
    measures = output["measures"]
    assert list(measures) == list(bench_pipeline.MEASURES)
    assert all(m["value"] > 0 and m["unit"] == bench_pipeline.UNITS[name] for name, m in measures.items())
    # frames: 5 demonstration frames per episode, then at most 6 steps and the reset frame
    assert 4 * (5 + 2) <= measures["dataset_generation"]["frames"] <= 4 * (5 + 7)
    assert measures["evaluation"]["episodes"] == 2 and measures["dagger_collection"]["episodes"] == 2
    assert measures["evaluation"]["num_agents"] == 2 and measures["dagger_collection"]["num_agents"] == 2
    training = measures["training"]
    assert 1 <= training["labelled_steps"] <= 16 * 6 and training["gradient_steps"] == 1
    assert training["flops"] > 0 and training["flops_per_s"] > 0
    # the replayed kernels carry every FLOP the counter saw, in less time than the steps took
    assert training["kernel_flops"] == training["flops"] and 0 < training["kernel_seconds"]
    assert training["kernel_distinct_calls"] <= training["kernel_calls"]
    assert (tmp_path / "new" / "bc_data" / "meta.json").exists()  # the training dataset, kept across repeats


def test_a_worker_imports_the_packages_of_its_own_tree(tmp_path):
    """Importing the driver module (as the worker does) must not put this checkout's packages
    ahead of the tree on ``PYTHONPATH``: otherwise the baseline would measure the working tree."""
    tree = tmp_path / "tree"
    (tree / "spf_rl").mkdir(parents=True)
    (tree / "spf_rl" / "__init__.py").write_text("")
    code = "import bench_pipeline, json, spf_rl; print(json.dumps({'spf_rl_file': spf_rl.__file__}))"
    output = bench_baseline.run_json_child(["-c", code], tree, after=[ROOT / "benchmarks"])
    assert Path(output["spf_rl_file"]).resolve() == (tree / "spf_rl" / "__init__.py").resolve()


def test_a_child_that_imported_another_tree_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(bench_pipeline, "run_json_child", lambda argv, tree, timeout=None, after=(): _output({"training": 1.0}))
    with pytest.raises(RuntimeError, match="imported spf_rl from"):
        bench_pipeline._child(["training"], bench_pipeline.QUICK_SIZES, tmp_path, tmp_path / "baseline")

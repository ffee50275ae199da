"""benchmarks/bench_pipeline.py: the baseline worktree, interleaved medians, the JSON and its targets, bad options,
and a tiny smoke run of every measure against the working tree (a smoke run, not a result)."""
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


def _output(values: dict[str, float], raw_fps: float = 1000.0) -> dict:
    """A worker's output with these measure values (canned)."""
    measures = {name: {"value": value, "unit": bench_pipeline.UNITS[name]} for name, value in values.items()}
    if "collection" in measures:
        measures["collection"]["raw_fps"] = raw_fps
    return {"measures": measures, "branches": {"collection": ["default env"]}, "torch_threads": 2}


def test_repeats_are_interleaved_and_each_figure_is_the_median():
    old = iter([3.0, 1.0, 2.0])
    new = iter([10.0, 30.0, 20.0])
    order = []

    def fake_measure(side: str, repeat: int) -> dict:
        order.append(side)
        return _output({"evaluation": next(old if side == "old" else new)})

    runs = bench_baseline.interleaved_runs(fake_measure, 3)
    assert order == ["old", "new"] * 3
    summary = bench_pipeline.summarise(runs, ["evaluation"])
    evaluation = summary["measures"]["evaluation"]
    assert (evaluation["old"], evaluation["new"], evaluation["unit"]) == (2.0, 20.0, "episodes/s")
    assert evaluation["old_repeats"] == [3.0, 1.0, 2.0] and evaluation["new_repeats"] == [10.0, 30.0, 20.0]
    assert summary["speedups"] == {
        "dataset_generation": None, "dagger_collection": None, "evaluation": 10.0, "evaluation_repeat": None, "bc_training": None
    }
    assert summary["targets"]["evaluation"]["holds"] is True
    assert summary["targets"]["bc_training"] == {"target": 1.5, "of": "speed-up new/old", "measured": None, "holds": None}
    assert summary["raw_fps"] is None and summary["store_lookup_ratio_to_raw"] is None


@contextlib.contextmanager
def _no_worktree(repo, sha, path=None):
    yield Path("/nonexistent-baseline")


def test_json_layout_and_targets_from_canned_worker_outputs(tmp_path, monkeypatch):
    old = {"dataset_generation": 10.0, "dagger_collection": 4.0, "evaluation": 10.0, "evaluation_repeat": 10.0,
           "bc_training": 100.0, "collection": 500.0}
    new = {"dataset_generation": 50.0, "dagger_collection": 8.0, "evaluation": 30.0, "evaluation_repeat": 40.0,
           "bc_training": 150.0, "collection": 900.0}
    canned = {
        "old": [_output(old, raw_fps=2000.0) for _ in range(3)],
        "new": [_output(new, raw_fps=raw) for raw in (1000.0, 900.0, 1100.0)],
    }
    seen = {}

    def fake_benchmark(args, trees, scratch):
        seen.update(trees=trees, sizes=args.sizes, repeats=args.repeats)
        return canned

    monkeypatch.setattr(bench_pipeline, "baseline_worktree", _no_worktree)
    monkeypatch.setattr(bench_pipeline, "run_benchmark", fake_benchmark)
    out = tmp_path / "results" / "pipeline.json"
    result = bench_pipeline.main(["--quick", "--baseline", "HEAD", "--output", str(out)])
    written = json.loads(out.read_text())
    assert written == json.loads(json.dumps(result))
    assert not list(out.parent.glob(".*.tmp*"))  # written through a temporary file, renamed
    assert seen["trees"] == {"old": Path("/nonexistent-baseline"), "new": ROOT}
    assert seen["sizes"] == bench_pipeline.QUICK_SIZES and seen["repeats"] == 3
    assert written["baseline_commit"] == _git(ROOT, "rev-parse", "HEAD") and written["quick"] is True
    for key in ("raw_fps", "measures", "speedups", "store_lookup_ratio_to_raw", "targets", "setup", "machine", "runs"):
        assert key in written
    assert set(written["speedups"]) == {"dataset_generation", "dagger_collection", "evaluation", "evaluation_repeat", "bc_training"}
    assert written["speedups"]["dataset_generation"] == 5.0 and written["speedups"]["dagger_collection"] == 2.0
    assert written["speedups"]["evaluation_repeat"] == 4.0
    bc = written["measures"]["bc_training"]
    assert (bc["old"], bc["new"], bc["unit"], bc["new_over_old"]) == (100.0, 150.0, "labelled steps/s", 1.5)
    assert written["raw_fps"] == 1000.0  # the median of the new tree's raw loop
    assert written["store_lookup_ratio_to_raw"] == 0.9
    assert written["raw_loop"]["old_collection_ratio_to_its_raw"] == 0.25
    targets = written["targets"]
    assert {name: targets[name]["holds"] for name in targets} == {
        "dataset_generation": True,  # 5.0 >= 4
        "evaluation": False,  # 3.0 < 4
        "bc_training": True,  # 1.5 >= 1.5
        "collection": False,  # 0.9 < 1.0
    }
    assert targets["collection"]["measured"] == 0.9 and targets["collection"]["target"] == 1.0
    assert written["setup"]["repeats"] == 3 and written["setup"]["sizes"]["dataset_episodes"] == 128
    assert written["machine"]["cpu_count"] >= 1 and written["runs"] == canned


#: Bad command lines; the option named first is the one the error must name.
BAD_COMMAND_LINES = [
    "--repeats 0",
    "--repeats 2",
    "--only evaluation,nonsense",
    "--only ,",
    "--workers 0",
    "--baseline 0123456789abcdef0123",
]


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


def test_smoke_every_measure_runs_against_the_working_tree(tmp_path):
    """A tiny run of the worker (the script the benchmark runs in each tree), here on the working tree only."""
    sizes = dataclasses.replace(
        bench_pipeline.Sizes(),
        dataset_episodes=4, dagger_episodes=2, num_agents=2, eval_episodes=2, eval_agents=2,
        bc_steps=1, bc_warmup_steps=0, collection_batches=1, raw_chunks=1, raw_chunk_frames=20,
        num_houses=1, demo_length=5, max_steps=6, image_size=32, workers=1, store_demos=4,
    )
    argv = bench_pipeline._worker_argv(bench_pipeline.MEASURES, sizes, tmp_path / "new", threads=1)
    output = bench_baseline.run_json_child(argv, ROOT, timeout=300)
    assert output["spf_rl_file"] == str(ROOT / "spf_rl" / "__init__.py")
    measures = output["measures"]
    assert list(measures) == list(bench_pipeline.MEASURES)
    assert all(m["value"] > 0 and m["unit"] == bench_pipeline.UNITS[name] for name, m in measures.items())
    assert measures["dataset_generation"]["episodes"] == 4 and measures["evaluation"]["episodes"] == 2
    assert measures["bc_training"]["labelled_steps"] <= 4 * 6  # at most every step of the 4 episodes
    assert measures["collection"]["raw_fps"] > 0 and measures["collection"]["frames_per_batch"] == 2 * 6
    assert (tmp_path / "new" / "bc_data" / "meta.json").exists()  # the first dataset built, kept for bc_training
    assert output["branches"]["collection"][0].startswith("demo store")  # this tree collects from a demo store


def test_a_worker_imports_the_packages_of_its_own_tree(tmp_path):
    """Importing the driver module (as the worker does) must not put this checkout's packages
    ahead of the tree on ``PYTHONPATH``: otherwise "old" would measure the working tree."""
    tree = tmp_path / "tree"
    (tree / "spf_rl").mkdir(parents=True)
    (tree / "spf_rl" / "__init__.py").write_text("")
    code = "import bench_pipeline, json, spf_rl; print(json.dumps({'spf_rl_file': spf_rl.__file__}))"
    output = bench_baseline.run_json_child(["-c", code], tree, after=[ROOT / "benchmarks"])
    assert Path(output["spf_rl_file"]).resolve() == (tree / "spf_rl" / "__init__.py").resolve()


def test_a_worker_that_imported_another_tree_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(bench_pipeline, "run_json_child", lambda argv, tree, timeout=None: {
        **_output({"evaluation": 1.0}), "spf_rl_file": str(ROOT / "spf_rl" / "__init__.py")})
    args = bench_pipeline.parse_args(["--quick", "--only", "evaluation"])
    with pytest.raises(RuntimeError, match="the old worker imported spf_rl from"):
        bench_pipeline.run_benchmark(args, {"old": tmp_path / "baseline", "new": ROOT}, tmp_path)

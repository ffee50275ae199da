"""Every recipe refuses a bad value before any work: one line ``<recipe>: error: <message>`` on
standard error naming the parameter, exit status 2, no traceback, nothing written.

Each kind of bad value is tried on every recipe that takes it:

* an unknown config key (``modle=spf``), for the recipes with a config;
* a bad model-config value (a sparsity outside (0, 1], a negative or zero size), for the recipes
  with a config;
* a missing checkpoint path, for the recipes that take a checkpoint (a config's ``checkpoint``, a
  path or shipped name on the command line, a run directory);
* a bad value of its own for the recipes that take neither.

Each of these cases runs the recipe as its script does (its ``__main__`` block, from the repository
root, in this process) with every output redirected into a temporary directory, which must stay
empty. A few (:data:`SCRIPT_CASES`) also run as ``python recipes/<recipe>.py`` in a new interpreter.

More bad values (``--sparsity`` of the recipes that evaluate a checkpoint, a file that is not a
checkpoint for each way the recipes load one, an unknown shipped name) run each recipe's ``main()``
in this process, and the checks the recipes share (the model config, :func:`spf_rl.hub.checkpoint_argument`)
are tested on their own.
"""
from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Case:
    """``python recipes/<recipe> <args>``; ``{out}`` in an argument is a directory that must stay
    empty (not even made), ``{tmp}`` the case's temporary directory. The error line must hold every
    string of ``names``."""

    id: str
    recipe: str
    args: tuple[str, ...]
    names: tuple[str, ...]


def case(id: str, recipe: str, args: str, *names: str) -> Case:
    return Case(id, recipe, tuple(args.split()), names)


#: BC-like outputs, all under {out}.
BC_OUT = "output_dir={out}/run data_dir={out}/data"
TABLE1_OUT = "--quick --from-checkpoints --rows open_loop --out {out}/table --eval-dir {out}/eval --checkpoints {out}/checkpoints"
MISSING = "{tmp}/missing.pt"

CASES = [
    # an unknown config key
    case("bc-unknown-key", "bc.py", f"modle=spf {BC_OUT}", "invalid configuration: Key 'modle' not in 'BCConfig'", "Did you mean: 'model'?"),
    case("bc_lengths-unknown-key", "bc_lengths.py", "modle=spf output_dir={out}/run data_root={out}/data",
         "invalid configuration: Key 'modle' not in 'MixedLengthConfig'", "Did you mean: 'model'?"),
    case("make_dataset-unknown-key", "make_dataset.py", "modle=spf data_dir={out}/data", "invalid configuration: Key 'modle' not in 'BCConfig'"),
    case("dagger-unknown-key", "dagger.py", "modle=spf output_dir={out}/run", "invalid configuration: Key 'modle' not in 'DAggerConfig'"),
    case("ppo_finetune-unknown-key", "ppo_finetune.py", "modle=spf output_dir={out}/run", "invalid configuration: Key 'modle' not in 'PPOConfig'"),
    case("make_demo_store-unknown-key", "make_demo_store.py", "modle=spf root={out}/store",
         "invalid configuration: Key 'modle' not in 'MakeDemoStoreConfig'"),
    case("table1-unknown-key", "table1.py", f"{TABLE1_OUT} modle=spf", "invalid configuration: Key 'modle' not in 'BCConfig'"),
    # a bad model-config value
    case("bc-sparsity", "bc.py", f"--quick sparsity=1.7 {BC_OUT}", "model.sparsity", "(0, 1]", "1.7"),
    case("bc_lengths-hidden_size", "bc_lengths.py", "--quick model.hidden_size=-8 output_dir={out}/run data_root={out}/data",
         "model.hidden_size must be a positive int", "-8"),
    case("make_dataset-feature_dim", "make_dataset.py", "--quick model.feature_dim=0 data_dir={out}/data", "model.feature_dim must be a positive int"),
    case("table1-sparsity", "table1.py", f"{TABLE1_OUT} sparsity=1.7", "model.sparsity", "(0, 1]"),
    case("dagger-rounds", "dagger.py", "--quick rounds=-1 output_dir={out}/run", "rounds must be", "-1"),
    case("dagger-anchor_radius", "dagger.py", "--quick anchor_radius=0 output_dir={out}/run", "anchor_radius must be a positive int", "0"),
    case("ppo_finetune-frames_per_batch", "ppo_finetune.py", "--quick frames_per_batch=-5 output_dir={out}/run", "frames_per_batch must be a positive int"),
    case("make_demo_store-num_demos", "make_demo_store.py", "store.num_demos=-3 root={out}/store", "num_demos", "-3"),
    # a missing checkpoint path
    case("dagger-missing-checkpoint", "dagger.py", f"--quick checkpoint={MISSING} output_dir={{out}}/run", "checkpoint", "missing.pt does not exist"),
    case("ppo_finetune-missing-checkpoint", "ppo_finetune.py", f"--quick checkpoint={MISSING} output_dir={{out}}/run",
         "checkpoint", "missing.pt does not exist"),
    case("evaluate-missing-checkpoint", "evaluate.py", f"{MISSING} --out {{out}}", "argument paths", "missing.pt does not exist"),
    case("visualize-missing-checkpoint", "visualize.py", f"{MISSING} --out {{out}}", "argument checkpoint", "missing.pt does not exist"),
    case("success_by_length-missing-checkpoint", "success_by_length.py", f"{MISSING} --out {{out}}", "argument checkpoints", "missing.pt does not exist"),
    case("pointer_trace-missing-checkpoint", "pointer_trace.py", f"--checkpoint {MISSING} --out {{out}}/trace.json",
         "argument --checkpoint", "missing.pt does not exist"),
    case("route_bench-missing-checkpoint", "route_bench.py", f"--models {MISSING} --out {{out}}/bench.json", "argument --models", "missing.pt"),
    case("teach-missing-checkpoint", "teach.py", f"--actions FFFFFFFFFF --checkpoint {MISSING} --out {{out}}", "--checkpoint", "missing.pt does not exist"),
    case("export-missing-checkpoint", "export.py", f"{MISSING} --out {{out}}/export", "argument checkpoint", "missing.pt does not exist"),
    case("start_check-missing-checkpoint", "start_check.py", f"{MISSING} --out {{out}}/checked.pt --results {{out}}/checked.json",
         "argument checkpoint", "missing.pt does not exist"),
    case("picking_study-missing-run", "picking_study.py", "{tmp}/missing_run --out {out}", "missing_run has no config.json and last.pt"),
    # the recipes that take neither a config nor a checkpoint
    case("paired-missing-json", "paired.py", "{tmp}/a.json {tmp}/b.json --out {out}/paired.json", "no evaluation JSON", "a.json"),
    case("expert_stats-episodes", "expert_stats.py", "--episodes 0 --output {out}/stats.json", "--episodes must be a positive int"),
    case("route_styles-lengths", "route_styles.py", "--lengths -5 --out {out}/routes.png", "--lengths", "-5"),
    case("conditions-episodes", "conditions.py", "--episodes 0 --out {out}/conditions.png --stats {out}/conditions.json",
         "--search and --episodes >= 1", "0"),
    case("sample_efficiency-lever", "sample_efficiency.py", "--levers faster --out {out}/study.json", "argument --levers", "faster"),
]


#: Cases also run as a new interpreter, ``python recipes/<recipe> <args>``: what only a fresh process shows
#: (a warning printed at import, an exit status through the interpreter) for the training, deployment and
#: teaching recipes' import chains. The rest run in this process (each new interpreter costs about 4 s of CPU
#: importing torch).
SCRIPT_CASES = ("bc-unknown-key", "export-missing-checkpoint", "teach-missing-checkpoint")


@dataclass(frozen=True)
class Outcome:
    returncode: int
    stderr: str
    written: list[str]  # paths under {out}, which must not even exist


def _arguments(case: Case, tmp: Path) -> list[str]:
    return [arg.replace("{out}", str(tmp / "out")).replace("{tmp}", str(tmp)) for arg in case.args]


def _written(tmp: Path) -> list[str]:
    out = tmp / "out"
    return [str(path.relative_to(tmp)) for path in [out, *out.rglob("*")] if path.exists()]


def run_script(case: Case, tmp: Path) -> Outcome:
    """The case as ``python recipes/<recipe> <args>`` from the repository root."""
    process = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / case.recipe), *_arguments(case, tmp)],
        cwd=ROOT, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=300,
    )
    return Outcome(process.returncode, process.stderr, _written(tmp))


def test_every_recipe_has_cases():
    """A new recipe gets its bad values here too."""
    recipes = {path.name for path in (ROOT / "recipes").glob("*.py")}
    assert recipes == {c.recipe for c in CASES}
    assert len({c.id for c in CASES}) == len(CASES)
    assert set(SCRIPT_CASES) <= {c.id for c in CASES}


def check_outcome(case: Case, outcome: Outcome) -> None:
    lines = [line for line in outcome.stderr.splitlines() if line.strip()]
    assert "Traceback" not in outcome.stderr, outcome.stderr
    assert len(lines) == 1, outcome.stderr
    assert lines[0].startswith(f"{case.recipe}: error: "), lines[0]
    for name in case.names:
        assert name in lines[0], lines[0]
    assert outcome.returncode == 2, outcome.stderr
    assert outcome.written == [], outcome.written


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_a_bad_value_is_one_line_naming_it_and_exit_2(case, tmp_path, run_recipe):
    """As its script runs it, in this process (the ``run_recipe`` fixture)."""
    status, stderr = run_recipe(case.recipe.removesuffix(".py"), _arguments(case, tmp_path))
    check_outcome(case, Outcome(status, stderr, _written(tmp_path)))


@pytest.mark.parametrize("case", [c for c in CASES if c.id in SCRIPT_CASES], ids=[c.id for c in CASES if c.id in SCRIPT_CASES])
def test_a_bad_value_given_to_a_new_interpreter_is_one_line_and_exit_2(case, tmp_path):
    check_outcome(case, run_script(case, tmp_path))


# More bad values, each recipe's main() in this process (no interpreter to start).

IN_PROCESS = [
    ("evaluate", "spf_random-s0.2-1 --sparsity 1.7", "--sparsity must be in (0, 1]"),
    ("evaluate", "spf-s0.8 --sparsity 0.4", "argument --sparsity: applies to random-sparsity models"),
    ("evaluate", "spf-s0.8 --model-type rpf", "argument paths: ", "holds a 'spf' model, but a 'rpf' model was asked for"),
    ("pointer_trace", "--checkpoint routes-spf --sparsity 1.7", "--sparsity must be in (0, 1]"),
    ("pointer_trace", "--checkpoint spf-s0.8", "argument --checkpoint: spf-s0.8: policy must use RPF's pointer rule"),
    # a file that is not a checkpoint, for each way the recipes load one
    ("evaluate", "corrupt.pt", "argument paths: checkpoint corrupt.pt is corrupt or not a checkpoint"),
    ("visualize", "corrupt.pt", "argument checkpoint: checkpoint corrupt.pt is corrupt"),
    ("success_by_length", "corrupt.pt", "argument checkpoints: checkpoint corrupt.pt is corrupt"),
    ("pointer_trace", "--checkpoint corrupt.pt", "argument --checkpoint: checkpoint corrupt.pt is corrupt"),
    ("route_bench", "--models corrupt.pt", "argument --models: ", "corrupt.pt"),
    ("teach", "--actions FFFFFFFFFF --checkpoint corrupt.pt", "--checkpoint: checkpoint corrupt.pt is corrupt"),
    ("dagger", "--quick checkpoint=corrupt.pt", "invalid configuration: checkpoint: checkpoint corrupt.pt is corrupt"),
    ("ppo_finetune", "--quick checkpoint=corrupt.pt", "invalid configuration: checkpoint: checkpoint corrupt.pt is corrupt"),
    ("visualize", "spf-s0.7", "argument checkpoint: unknown checkpoint name 'spf-s0.7'"),
    # repeat conditions (envs.conditions)
    ("evaluate", "spf-s0.8 --conditions fog@1", "--conditions: unknown condition 'fog'; allowed names are none, light"),
    ("evaluate", "spf-s0.8 --memory-mismatch 1.5", "--memory-mismatch must be a number in [0, 1], got 1.5"),
    ("route_bench", "--models spf-s0.8 --conditions light@-1", "argument --conditions: ", "the strength of 'light' must be a number in [0, 1]"),
    ("route_bench", "--models spf-s0.8 --conditions paint@1=-2", "argument --conditions: ", "the weight of 'paint@1.0' must be a finite number >= 0"),
    # the start check's calibration (recipes/start_check.py)
    ("start_check", "spf-s0.8 --out x.pt --results x.json --split house", "argument --split: must be one of ('train', 'val', 'test'), got 'house'"),
    ("start_check", "spf-s0.8 --out x.pt --results x.json --episodes 0", "argument --episodes: must be >= 1, got 0"),
    ("start_check", "spf-s0.8 --out x.pt --results x.json --max-false-alarm 1.5", "argument --max-false-alarm: must be in [0, 1), got 1.5"),
    ("start_check", "spf-s0.8 --out x.onnx --results x.json", "argument --out: must be a .pt file, got 'x.onnx'"),
    ("start_check", "action_only-s0 --out x.pt --results x.json", "argument checkpoint: a start check needs a model with visual memory"),
    ("start_check", "corrupt.pt --out x.pt --results x.json", "argument checkpoint: checkpoint corrupt.pt is corrupt"),
    ("start_check", "corrupt.pt --out corrupt.pt --results x.json", "argument checkpoint: checkpoint corrupt.pt is corrupt"),
]


@pytest.mark.parametrize("recipe, args, names", [(r, a, n) for r, a, *n in IN_PROCESS], ids=[f"{r}: {a}" for r, a, *_ in IN_PROCESS])
def test_more_bad_values_in_process(recipe, args, names, tmp_path, monkeypatch, capsys):
    """The same rule, in this process: from a directory holding ``corrupt.pt`` (not a checkpoint),
    where the recipe's default outputs would go, and which must hold nothing else after."""
    import importlib

    (tmp_path / "corrupt.pt").write_bytes(b"not a checkpoint\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [f"{recipe}.py"])  # the parser's prog, as from the command line
    with pytest.raises(SystemExit) as exit_info:
        importlib.import_module(recipe).main(args.split())
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"{recipe}.py: error: "), lines[0]
    for name in names:
        assert name in lines[0], lines[0]
    assert exit_info.value.code == 2
    assert sorted(path.name for path in tmp_path.iterdir()) == ["corrupt.pt"]


# The checks the recipes share, in this process (no recipe started).


@pytest.mark.parametrize(
    "override, message",
    [
        ("sparsity=0", r"model.sparsity must be a number in the range \(0, 1\]"),
        ("model.k=-1", "model.k must be an int >= 0"),
        ("model.feature_dim=-16", "model.feature_dim must be a positive int"),
        ("model.hidden_size=0", "model.hidden_size must be a positive int"),
        ("pointer=linear", "model.pointer_update must be one of"),
        ("model.initial_pointer_step=1", r"model.initial_pointer_step must be in \(-1, 1\)"),
        ("model.sparsity_range=[0.9,0.2]", "model.sparsity_range must be a pair"),
    ],
)
def test_the_model_config_is_checked_when_the_config_is_loaded(override, message):
    """Not when the policy is built, after the dataset: ``load_config`` refuses the value, naming its key."""
    from spf_rl.config import load_config
    from spf_rl.train.bc import BCConfig

    with pytest.raises(ValueError, match=f"^invalid configuration: {message}"):
        load_config(BCConfig, "bc", [override])


def _checkpoint_with(tmp_path: Path, **changes) -> Path:
    """A copy of the shipped ``spf-s0.8`` with payload entries replaced (``None``: removed)."""
    import torch

    from spf_rl.hub import checked_checkpoint

    payload = torch.load(checked_checkpoint("spf-s0.8"), weights_only=True)
    for key, value in changes.items():
        payload.pop(key) if value is None else payload.__setitem__(key, value)
    path = tmp_path / "changed.pt"
    torch.save(payload, path)
    return path


@pytest.mark.parametrize(
    "given, message",
    [
        ("{tmp}/missing.pt", "checkpoint file {tmp}/missing.pt does not exist."),
        ("{tmp}/", "checkpoint file {tmp}/ is a directory, not a checkpoint file."),
        ("spf-s0.7", "unknown checkpoint name 'spf-s0.7'; the shipped checkpoints are: "),
        ("{tmp}/corrupt.pt", "checkpoint {tmp}/corrupt.pt is corrupt or not a checkpoint (UnpicklingError: Weights only load failed)."),
        ("no model_config", "holds no valid model_config (KeyError: 'model_config')."),
        ("a bad model_config", "holds no valid model_config (ValueError: sparsity must be a number in the range (0, 1]"),
        ("other weights", "does not load into its 'spf' model (RuntimeError: Error(s) in loading state_dict for SPFPolicy: "),
        ("another model type", "holds a 'spf' model, but a 'rpf' model was asked for."),
    ],
)
def test_a_bad_checkpoint_is_one_line_naming_the_argument(given, message, tmp_path):
    """:func:`spf_rl.hub.checkpoint_argument`, which the recipes call before any work."""
    import torch

    from spf_rl.hub import checkpoint_argument

    (tmp_path / "corrupt.pt").write_bytes(b"not a checkpoint\n")
    model_type = None
    if given == "no model_config":
        given = str(_checkpoint_with(tmp_path, model_config=None))
    elif given == "a bad model_config":
        config = dict(torch.load(_checkpoint_with(tmp_path), weights_only=True)["model_config"], sparsity=1.7)
        given = str(_checkpoint_with(tmp_path, model_config=config))
    elif given == "other weights":
        given = str(_checkpoint_with(tmp_path, model={"not_a_parameter": torch.zeros(1)}))
    elif given == "another model type":
        given, model_type = "spf-s0.8", "rpf"
    with pytest.raises(ValueError) as refused:
        checkpoint_argument(given.replace("{tmp}", str(tmp_path)), "argument --checkpoint", model_type=model_type)
    text = str(refused.value)
    assert text.startswith("argument --checkpoint: ") and "\n" not in text, text
    assert message.replace("{tmp}", str(tmp_path)) in text, text


def test_a_good_checkpoint_is_returned_loaded():
    from spf_rl.hub import CHECKPOINT_DIR, checkpoint_argument

    checked = checkpoint_argument("spf-s0.8", "argument --checkpoint", model_type="spf")
    assert checked.path.relative_to(CHECKPOINT_DIR).as_posix() == "table1/spf-s0.8-seed2.pt"
    assert checked.payload["model_type"] == "spf" and checked.policy.config.sparsity == 0.8 and not checked.policy.training

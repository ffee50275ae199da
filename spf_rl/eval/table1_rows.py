"""The rows of Table 1 and the runs behind them: every row trained on one budget
(:data:`TABLE1_PRESET`) and every DAgger column by one rule (:data:`TABLE1_DAGGER_PRESET`), in
``runs/table1/``; how the seeds of its finished runs become per-seed checkpoints and a shipped name, and how every checkpoint is
scored on the table's episode sets (cached per episode). ``recipes/table1.py`` is the
command line (:class:`Table1Options`, :func:`spf_rl.cli.parse_names`, :func:`spf_rl.cli.parse_seeds`, then
:func:`reproduce`); :mod:`spf_rl.eval.table1` turns the records into the table.
"""
from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from envs.atomic_io import atomic_write
from spf_rl.config import load_config
from spf_rl.eval.table1 import CACHED_FIELDS, PACE_NOTE, Line, build_table, write_reports

logger = logging.getLogger(__name__)


#: Table 1's one training budget, every trained row's (``recipes/configs/bc_table1.yaml``).
TABLE1_PRESET = "bc_table1"
#: Table 1's one DAgger rule, every DAgger column's (``recipes/configs/dagger_table1.yaml``).
TABLE1_DAGGER_PRESET = "dagger_table1"
#: The table's run directories: ``<RUNS_DIR>/<line>-seed<S>``, a line being a row or ``dagger-<row>``.
RUNS_DIR = Path("runs/table1")
#: The table's training seeds; a line's name ships the best of these (and of any others asked for) by validation.
DEFAULT_SEEDS = (0, 1, 2)
#: Overrides of ``recipes/table1.py`` that reach the DAgger runs too (the others are BC keys).
DAGGER_OVERRIDE_KEYS = ("device", "optim.amp")


@dataclass(frozen=True)
class RowSpec:
    """A row of Table 1: what is trained (on :data:`TABLE1_PRESET`), with what overrides, and the paper's numbers.

    Attributes:
        trained: the row trains a model (open-loop replay does not).
        dagger: the row has a DAgger column (:data:`TABLE1_DAGGER_PRESET` from the row's BC runs).
    """

    name: str
    label: str
    model: str
    sparsity: float
    overrides: tuple[str, ...] = ()
    paper: tuple[float | None, float | None] = (None, None)
    eval_sparsities: tuple[float, ...] = ()
    trained: bool = True
    dagger: bool = False


#: Sparsities the random-sparsity model is evaluated at.
RANDOM_EVAL_SPARSITIES = (0.4, 0.6, 0.8, 1.0)
RANDOM_MODEL = "spf_random"
#: Paper: Table 1 (Habitat, MP3D), (success, SPL).
ROWS = (
    RowSpec("spf-s0.4", "SPF sparsity 0.4", "spf", 0.4, ("model=spf", "sparsity=0.4"), (0.782, 0.683)),
    RowSpec("spf-s0.6", "SPF sparsity 0.6", "spf", 0.6, ("model=spf", "sparsity=0.6"), (0.803, 0.724)),
    RowSpec("spf-s0.8", "SPF sparsity 0.8", "spf", 0.8, ("model=spf", "sparsity=0.8"), (0.819, 0.737), dagger=True),
    RowSpec("rpf-s1", "SPF at sparsity 1 (RPF as SPF)", "rpf", 1.0, ("model=rpf", "sparsity=1"), dagger=True),
    RowSpec("rpf_original-s1", "RPF (original)", "rpf_original", 1.0, ("model=rpf_original", "sparsity=1"),
            (0.833, 0.752), dagger=True),
    RowSpec("spf_rpf_pointer-s0.8", "SPF 0.8 with RPF's pointer rule (beyond the paper)", "spf", 0.8,
            ("model=spf", "sparsity=0.8", "model.pointer_update=rpf"), dagger=True),
    RowSpec("action_only-s0", "RPF action only", "action_only", 0.0, ("model=action_only",), (0.782, 0.648)),
    RowSpec("open_loop", "open-loop replay", "open_loop", 0.0, trained=False),
    RowSpec("spf_random-s0.2-1", "SPF random sparsity 0.2-1", RANDOM_MODEL, 0.8, ("model=spf_random",),
            eval_sparsities=RANDOM_EVAL_SPARSITIES),
)
ROW_BY_NAME = {row.name: row for row in ROWS}
#: Ordering claims, each "a > b" on the shared episodes: (a, b, text); lines absent from a run are skipped.
CLAIMS = (
    ("spf-s0.6", "spf-s0.4", "SPF 0.6 beats SPF 0.4"),
    ("spf-s0.8", "spf-s0.6", "SPF 0.8 beats SPF 0.6"),
    ("rpf-s1", "spf-s0.8", "full memory (SPF at sparsity 1) beats SPF 0.8"),
    ("rpf_original-s1", "spf-s0.8", "the original RPF beats SPF 0.8"),
    ("spf-s0.4", "action_only-s0", "SPF 0.4 beats action-only"),
    ("spf-s0.8", "action_only-s0", "SPF 0.8 beats action-only"),
    ("rpf_original-s1", "action_only-s0", "the original RPF beats action-only"),
    ("spf-s0.8", "open_loop", "SPF 0.8 beats open-loop replay"),
    ("action_only-s0", "open_loop", "action-only beats open-loop replay"),
    ("spf_rpf_pointer-s0.8", "spf-s0.8", "RPF's pointer rule improves SPF 0.8"),
    ("dagger-spf-s0.8", "spf-s0.8", "DAgger improves SPF 0.8"),
    ("dagger-rpf-s1", "rpf-s1", "DAgger improves SPF at sparsity 1"),
    ("dagger-rpf_original-s1", "rpf_original-s1", "DAgger improves the original RPF"),
    ("dagger-spf_rpf_pointer-s0.8", "spf_rpf_pointer-s0.8", "DAgger improves SPF 0.8 with RPF's pointer rule"),
    ("dagger-spf_rpf_pointer-s0.8", "dagger-spf-s0.8", "with DAgger, RPF's pointer rule improves SPF 0.8"),
    # one model, one schedule, only the memory it is given changes: the sparsity order without confounders
    ("spf_random-s0.2-1@0.6", "spf_random-s0.2-1@0.4", "random sparsity: 0.6 beats 0.4"),
    ("spf_random-s0.2-1@0.8", "spf_random-s0.2-1@0.6", "random sparsity: 0.8 beats 0.6"),
    ("spf_random-s0.2-1@1", "spf_random-s0.2-1@0.8", "random sparsity: 1 beats 0.8"),
    ("spf_random-s0.2-1@1", "spf_random-s0.2-1@0.4", "random sparsity: 1 beats 0.4"),
)
SETS = ("test", "extended")
#: Houses of the extended test set.
EXTENDED_HOUSES = 100
#: --quick: episodes per set, and where everything goes.
QUICK_EPISODES = 8
QUICK_DIR = Path("runs/table1_quick")
#: Where a part of the table (fewer rows, seeds or sets than the defaults) is written unless ``out`` is given, so
#: that it never overwrites the whole table in ``results/``.
PART_DIR = Path("runs/table1_part")
#: Validation episodes (teacher-forced) each checkpoint's pointer pace is measured on (:func:`pace_episodes`).
PACE_EPISODES = 64


def checkpoint_name(model: str, sparsity) -> str:
    """File name of a model's checkpoint: ``spf-s0.4.pt``, or ``spf_random-s0.2-1.pt`` for a range ``(0.2, 1.0)``."""
    if isinstance(sparsity, (tuple, list)):
        return f"{model}-s" + "-".join(f"{s:g}" for s in sparsity) + ".pt"
    return f"{model}-s{sparsity:g}.pt"


def seed_checkpoint(checkpoints: Path, line: str, seed: int) -> Path:
    """Per-seed checkpoint of a line (a row, or ``dagger-<row>``): ``<checkpoints>/table1/<line>-seed<S>.pt``."""
    return checkpoints / "table1" / f"{line}-seed{seed}.pt"


def table_lines(rows: list[RowSpec], demo_length: int, image_size: int) -> list[Line]:
    """The lines of the table: one per row, one per evaluated sparsity of the random model, and DAgger lines."""
    from spf_rl.modules.views import model_memory_bytes

    def memory(model: str, sparsity: float) -> int:
        return demo_length if model == "open_loop" else model_memory_bytes(model, demo_length, sparsity, image_size)

    lines = []
    for row in rows:
        common = dict(row=row.name, model=row.model, paper_success=row.paper[0], paper_spl=row.paper[1])
        if row.eval_sparsities:
            for s in row.eval_sparsities:
                lines.append(Line(name=f"{row.name}@{s:g}", label=f"{row.label}, at {s:g}", sparsity=s,
                                  memory_bytes=memory(row.model, s), checkpoint_stem=row.name, **common))
        else:
            lines.append(Line(name=row.name, label=row.label, sparsity=row.sparsity,
                              memory_bytes=memory(row.model, row.sparsity), checkpoint_stem=row.name, **common))
        if row.dagger:
            lines.append(Line(name=f"dagger-{row.name}", label=f"DAgger from {row.label}", sparsity=row.sparsity,
                              memory_bytes=memory(row.model, row.sparsity), checkpoint_stem=f"dagger-{row.name}",
                              dagger_of=row.name, row=row.name, model=row.model))
    return lines


# ---------------------------------------------------------------------- configs
def preset_of(row: RowSpec, quick: bool) -> str | None:
    """The training schedule of a row: :data:`TABLE1_PRESET`, or ``bc_quick`` with ``--quick`` (none untrained)."""
    if not row.trained:
        return None
    return "bc_quick" if quick else TABLE1_PRESET


def run_dir(line: str, seed: int, quick: bool = False) -> Path:
    """The run directory of a line (a row, or ``dagger-<row>``) and seed: ``runs/table1/<line>-seed<S>``."""
    return (QUICK_DIR / "runs" if quick else RUNS_DIR) / f"{line}-seed{seed}"


def row_config(row: RowSpec, seed: int, overrides: list[str], quick: bool):
    """The ``BCConfig`` of one row and seed: the one schedule (``bc_quick`` with ``--quick``), the row's
    keys, its run directory and ``overrides``."""
    from spf_rl.train.bc import BCConfig

    items = [*row.overrides, f"seed={seed}", f"output_dir={run_dir(row.name, seed, quick)}", *overrides]
    return load_config(BCConfig, "bc", items, preset=preset_of(row, quick))


def eval_sets(overrides: list[str], quick: bool) -> dict:
    """``{"test": EvalConfig, "extended": EvalConfig}``: the schedule's test config, and the same on 100 houses."""
    from spf_rl.train.bc import BCConfig

    test = load_config(BCConfig, "bc", overrides, preset=TABLE1_PRESET).test  # sized as the training episodes
    if quick:
        test = dataclasses.replace(test, num_episodes=QUICK_EPISODES, num_agents=QUICK_EPISODES)
    return {"test": test, "extended": dataclasses.replace(test, episodes=test.episodes.replace(num_houses=EXTENDED_HOUSES))}


def pace_episodes(overrides: Sequence[str], quick: bool):
    """The episodes every checkpoint's pointer pace is measured on (:func:`pointer_paces`): the training
    data's config on the validation split, :data:`PACE_EPISODES` episodes (:data:`QUICK_EPISODES` with
    ``--quick``) of seed ``VAL_SEED``, built once under ``data/`` like a training dataset."""
    from spf_rl.data import EpisodeDataset
    from spf_rl.evaluation import VAL_SEED
    from spf_rl.train.bc import BCConfig

    base = load_config(BCConfig, "bc", list(overrides), preset=TABLE1_PRESET)
    count = QUICK_EPISODES if quick else PACE_EPISODES
    episodes = base.data.episodes.replace(split="val", seed=VAL_SEED)
    data = dataclasses.replace(base.data, episodes=episodes, num_episodes=count, chunk_size=min(count, base.data.chunk_size))
    root = data.default_dir()
    dataset = EpisodeDataset.build(root, data, base.num_workers, progress=False)
    return dataset[list(range(len(dataset)))], root


def pointer_paces(
    lines: Sequence[Line], seeds: Sequence[int], checkpoints: Path, overrides: Sequence[str], quick: bool, device: str
) -> tuple[dict, dict | None]:
    """``{checkpoint stem: {seed: pace}}``: :func:`~spf_rl.pointer_pace.pointer_pace` of every per-seed
    checkpoint there is (a pace below :data:`~spf_rl.pointer_pace.BACKWARD_PACE`: the pointer runs
    backwards), and what it was measured on (``None`` when there was no checkpoint): the episodes of
    :func:`pace_episodes`, built at the first checkpoint."""
    from spf_rl.hub import policy_from_checkpoint
    from spf_rl.pointer_pace import pointer_pace

    paces: dict = {}
    episodes = root = None
    for line in lines:
        if line.model == "open_loop" or line.checkpoint_stem in paces:
            continue
        stem = paces.setdefault(line.checkpoint_stem, {})
        for seed in seeds:
            checkpoint = seed_checkpoint(checkpoints, line.checkpoint_stem, seed)
            if not checkpoint.exists():
                continue
            if episodes is None:
                episodes, root = pace_episodes(overrides, quick)
            policy = policy_from_checkpoint(checkpoint, expected_model_type=line.model, device=device)[0]
            stem[str(seed)] = pointer_pace(policy, episodes)
    info = None if root is None else {"episodes": len(episodes), "dataset": root.as_posix(), "description": PACE_NOTE}
    return paces, info


def dagger_config(row: RowSpec, seed: int, overrides: Sequence[str] = ()):
    """The ``DAggerConfig`` of a row's DAgger run for ``seed`` (``None`` without a DAgger column): the one
    DAgger rule, from the row's BC run, aggregating that run's BC data; of ``overrides`` only the keys of
    :data:`DAGGER_OVERRIDE_KEYS` apply."""
    if not row.dagger:
        return None
    from spf_rl.train.dagger import DAggerConfig

    bc = row_config(row, seed, list(overrides), quick=False)
    items = [f"seed={seed}", f"checkpoint={Path(bc.output_dir) / 'best.pt'}",
             f"output_dir={run_dir(f'dagger-{row.name}', seed)}",
             *(item for item in overrides if item.split("=", 1)[0] in DAGGER_OVERRIDE_KEYS)]
    return dataclasses.replace(load_config(DAggerConfig, "dagger", items, preset=TABLE1_DAGGER_PRESET), bc_data=bc.data)


def budgets(overrides: Sequence[str] = ()) -> dict:
    """The table's one budget: BC gradient steps and episodes, DAgger rounds and gradient steps."""
    from spf_rl.train.bc import BCConfig
    from spf_rl.train.dagger import DAggerConfig

    bc = load_config(BCConfig, "bc", list(overrides), preset=TABLE1_PRESET)
    dagger = load_config(DAggerConfig, "dagger", [], preset=TABLE1_DAGGER_PRESET)
    steps_per_epoch = -(-bc.data.num_episodes // bc.optim.batch_size)
    return {
        "bc": {"preset": TABLE1_PRESET, "gradient_steps": bc.optim.epochs * steps_per_epoch,
               "episodes": bc.data.num_episodes, "batch_episodes": bc.optim.batch_size},
        "dagger": {"preset": TABLE1_DAGGER_PRESET, "rounds": dagger.rounds, "episodes_per_round": dagger.episodes_per_round,
                   "gradient_steps": dagger.rounds * dagger.steps_per_round, "val_seed": dagger.val.episodes.seed},
    }


# --------------------------------------------------------------------- training
def copy_atomic(source: Path, target: Path) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(target, lambda handle: handle.write(source.read_bytes()), binary=True)


def shipped_names(checkpoints: Path) -> dict[str, str]:
    """The shipped names of a checkpoint directory's manifest (none before its first)."""
    from spf_rl.hub import MANIFEST_NAME, read_manifest

    return read_manifest(checkpoints)["names"] if (checkpoints / MANIFEST_NAME).is_file() else {}


def ship_best(checkpoints: Path, line: str, scores: dict) -> dict | None:
    """Ship the per-seed checkpoint of the seed with the best validation ``(success, spl)`` as the name
    ``line``: the manifest maps the name to that file (no copy: each file is stored once)."""
    from spf_rl.hub import write_manifest

    if not scores:
        return None
    seed = max(scores, key=lambda s: (*scores[s], -s))
    target = seed_checkpoint(checkpoints, line, seed).relative_to(checkpoints).as_posix()
    write_manifest(checkpoints, {**shipped_names(checkpoints), line: target})
    logger.info("%s: seed %d is the best by validation (success %.3f): shipped as %s", line, seed, scores[seed][0], target)
    return {"seed": seed, "val_success": scores[seed][0], "val_spl": scores[seed][1]}


def checkpoint_policy_sha256(path: Path) -> str | None:
    """The :func:`~spf_rl.records_cache.policy_sha256` of the policy a checkpoint file holds."""
    from spf_rl.hub import policy_from_checkpoint
    from spf_rl.records_cache import policy_sha256

    return policy_sha256(policy_from_checkpoint(path)[0])


def holds_run_weights(target: Path, directory: Path) -> bool:
    """Whether the per-seed checkpoint ``target`` holds a finished run's best weights: the same bytes as the
    run's ``best.pt``, or, where a clone holds the run without it (a finished run's ``.pt`` files are not
    committed: its weights are the per-seed checkpoint), the weights its test records are keyed by
    (``test_episodes.json``, :func:`~spf_rl.records_cache.policy_sha256`)."""
    from spf_rl.records_cache import TEST_EPISODES_FILE

    if not target.exists():
        return False
    if (directory / "best.pt").exists():
        return target.read_bytes() == (directory / "best.pt").read_bytes()
    records = directory / TEST_EPISODES_FILE
    stored = (json.loads(records.read_text()).get("key") or {}).get("policy_sha256") if records.exists() else None
    return stored is not None and checkpoint_policy_sha256(target) == stored


def keep_run(checkpoints: Path, line: str, seed: int, directory: Path, best_key: str) -> tuple[float, float] | None:
    """A finished run's validation ``(success, spl)`` (``None``: not finished), its ``best.pt`` copied to the
    line's per-seed checkpoint where that file is missing or another (an earlier run's: this run supersedes it),
    and the manifest rewritten to list that file's hash (the names it ships stay as they are).

    A finished run without its ``best.pt`` (a clean clone) gets it back from the per-seed checkpoint when that
    file holds the run's weights (:func:`holds_run_weights`), so that its DAgger column can start from it;
    otherwise the run's weights are lost, and a ``FileNotFoundError`` names both files."""
    from spf_rl.hub import write_manifest

    results = directory / "results.json"
    if not results.exists():
        return None
    target, best = seed_checkpoint(checkpoints, line, seed), directory / "best.pt"
    if not best.exists():
        if not holds_run_weights(target, directory):
            raise FileNotFoundError(
                f"{directory} finished, but its weights are neither in {best} nor in {target}: restore one of them "
                f"(git history keeps the checkpoint), or delete {results} to train the run again"
            )
        copy_atomic(target, best)
    elif not target.exists() or target.read_bytes() != best.read_bytes():
        copy_atomic(best, target)
        write_manifest(checkpoints, shipped_names(checkpoints))  # the new file's hash, now, not after every run
    record = json.loads(results.read_text())[best_key]
    prefix = "val_" if best_key == "best" else ""
    return record[f"{prefix}success"], record[f"{prefix}spl"]


def train_missing(
    rows: list[RowSpec], seeds: list[int], overrides: list[str], checkpoints: Path, quick: bool, train: bool = True
) -> dict:
    """Train (or resume) every row x seed whose run has not finished (with ``train``; seed 0 of every row
    first, each DAgger column right after its row), copy each finished run's best checkpoint to its per-seed
    name, and ship each line's best seed by validation once every seed of the line has a finished run;
    returns ``{line: shipped}``. ``--quick`` trains no DAgger.

    The seeds a name ships from are ``seeds`` and :data:`DEFAULT_SEEDS` together: ``--seeds 2`` trains seed 2
    only, yet ships the best of seeds 0, 1 and 2, never seed 2 alone. A line whose ship seeds are not all
    finished runs of this recipe keeps its shipped name as it is (its per-seed files may be other runs', see
    :func:`trained_on`)."""
    from spf_rl.train.bc import train_bc
    from spf_rl.train.dagger import train_dagger

    trained = [row for row in rows if row.trained]
    scores: dict[str, dict[int, tuple[float, float]]] = {}
    ship_seeds = sorted({*seeds, *DEFAULT_SEEDS})
    for seed in ship_seeds:
        train_seed = train and seed in seeds
        for row in trained:
            config = row_config(row, seed, overrides, quick)
            bc_dir = Path(config.output_dir)
            if train_seed and not (bc_dir / "results.json").exists():
                logger.info("training %s seed %d in %s (preset %s)", row.name, seed, bc_dir, preset_of(row, quick))
                train_bc(config)
            if (bc_score := keep_run(checkpoints, row.name, seed, bc_dir, "val_best")) is not None:
                scores.setdefault(row.name, {})[seed] = bc_score
            if not row.dagger or quick:
                continue
            dagger = dagger_config(row, seed, overrides)
            dagger_dir = Path(dagger.output_dir)
            if train_seed and bc_score is not None and not (dagger_dir / "results.json").exists():
                logger.info("DAgger from %s seed %d in %s", row.name, seed, dagger_dir)
                train_dagger(dagger)
            if (score := keep_run(checkpoints, f"dagger-{row.name}", seed, dagger_dir, "best")) is not None:
                scores.setdefault(f"dagger-{row.name}", {})[seed] = score
    shipped = {}
    for line in (name for row in trained for name in (row.name, *([f"dagger-{row.name}"] if row.dagger and not quick else []))):
        line_scores = scores.get(line, {})
        if set(line_scores) != set(ship_seeds):
            logger.info("%s: seeds %s have no finished run here yet: the name %s is left as it is", line,
                        sorted(set(ship_seeds) - set(line_scores)), line)
            continue
        shipped[line] = ship_best(checkpoints, line, line_scores)
    if checkpoints.is_dir():  # per-seed files copied above are listed too
        from spf_rl.hub import write_manifest

        write_manifest(checkpoints, shipped_names(checkpoints))
    return shipped


def run_restarts(stem: str, seed, quick: bool) -> list[dict]:
    """The pointer-collapse guard's restarts of a line's run (``pointer_restarts`` of its ``results.json``)."""
    results = run_dir(stem, int(seed), quick) / "results.json"
    return json.loads(results.read_text()).get("pointer_restarts", []) if results.exists() else []


def trained_on(lines: Sequence[Line], seeds: Sequence[int], checkpoints: Path, quick: bool) -> dict:
    """``{line: {seed: CPU}}`` for the trained lines: the seeds whose per-seed checkpoint is the best of this
    recipe's finished run, each with the CPU model that trained it (``machine_this_run`` of its
    ``results.json``; ``None`` where the run did not record it). A seed's result depends on the CPU model, so a
    rerun elsewhere matches the table only on the same model. A per-seed file of another run is scored as it
    is and has no entry."""
    sources: dict = {}
    for line in lines:
        if line.model == "open_loop" or line.checkpoint_stem in sources:
            continue
        entry = sources.setdefault(line.checkpoint_stem, {})
        for seed in seeds:
            target = seed_checkpoint(checkpoints, line.checkpoint_stem, seed)
            results = run_dir(line.checkpoint_stem, seed, quick) / "results.json"
            if results.exists() and holds_run_weights(target, results.parent):
                entry[str(seed)] = json.loads(results.read_text()).get("machine_this_run", {}).get("cpu_model")
    return sources


# ------------------------------------------------------------------- evaluation
def eval_config(config, line: Line):
    """The evaluation config of a line: open-loop replay ignores the camera, so its (same) episodes are not rendered."""
    return dataclasses.replace(config, render=False) if line.model == "open_loop" else config


def line_policy(line: Line, checkpoint: Path | None, device: str):
    """The policy a line plays: open-loop replay, or the checkpoint's on ``device`` (a random-sparsity
    line's at the line's sparsity)."""
    from spf_rl.hub import policy_from_checkpoint
    from spf_rl.modules import OpenLoopPolicy

    if checkpoint is None:
        return OpenLoopPolicy()
    policy = policy_from_checkpoint(checkpoint, expected_model_type=line.model, device=device)[0]
    if line.model == RANDOM_MODEL:
        policy.set_sparsity(line.sparsity)
    return policy


def evaluate_line(line: Line, policy, config) -> list[dict]:
    """Per-episode records of one line's policy (:func:`line_policy`) on one evaluation set."""
    from spf_rl.evaluation import evaluate_policy

    return evaluate_policy(policy, config, progress=False)[1]


def run_test_records(line: Line, seed: int | None, key: dict) -> list[dict] | None:
    """The per-episode records a run left under ``key`` (the same weights, as played, on the same episodes:
    its ``test_episodes.json``; a finished run tests its best weights on ``bc_table1``'s test set), or ``None``.
    Evaluation is deterministic, so the records are the ones evaluating again would give (checked on the first
    runs: identical, episode by episode)."""
    from spf_rl.records_cache import TEST_EPISODES_FILE, read_records

    if seed is None:
        return None
    found = read_records(run_dir(line.checkpoint_stem, seed) / TEST_EPISODES_FILE, key)
    if found is not None:
        logger.info("%s seed %d: reusing its run's test records of these weights on these episodes", line.name, seed)
    return found


def cache_path(eval_dir: Path, set_name: str, line: str, seed: int | None) -> Path:
    """Where the records of one line x seed x set are cached: ``<eval_dir>/<set>/<line>[-seed<S>].json``."""
    return eval_dir / set_name / (line + ("" if seed is None else f"-seed{seed}") + ".json")


def evaluate_all(
    lines: list[Line], seeds: list[int], sets: dict, checkpoints: Path, eval_dir: Path, device: str
) -> tuple[dict, list[dict]]:
    """Records ``{line: {set: {seed: records}}}`` of every line x seed x set whose checkpoint exists, from
    the cache (:mod:`spf_rl.records_cache`: the same weights on the same episodes) or evaluated now (then
    cached), and the list of what is missing."""
    from spf_rl.records_cache import cached_records, records_key

    evaluations: dict = {line.name: {name: {} for name in sets} for line in lines}
    missing = []
    for line in lines:
        line_seeds = [None] if line.model == "open_loop" else seeds
        for seed in line_seeds:
            checkpoint = None if seed is None else seed_checkpoint(checkpoints, line.checkpoint_stem, seed)
            if checkpoint is not None and not checkpoint.exists():
                entry = {"line": line.checkpoint_stem, "seed": seed, "checkpoint": str(checkpoint)}
                missing += [entry] if entry not in missing else []  # the random model's lines share checkpoints
                continue
            policy = line_policy(line, checkpoint, device)
            for set_name, config in sets.items():
                config = eval_config(config, line)
                key = records_key(config, policy)

                def evaluate(line=line, seed=seed, set_name=set_name, config=config, key=key, policy=policy) -> list[dict]:
                    if (records := run_test_records(line, seed, key)) is not None:
                        return records
                    logger.info("evaluating %s seed %s on the %s set (%d episodes)", line.name, seed, set_name,
                                config.num_episodes)
                    return evaluate_line(line, policy, config)

                evaluations[line.name][set_name][seed] = cached_records(
                    cache_path(eval_dir, set_name, line.name, seed), key, evaluate, CACHED_FIELDS,
                    line=line.name, seed=seed, set=set_name, checkpoint=None if checkpoint is None else str(checkpoint),
                )
    return evaluations, missing


# ---------------------------------------------------------------------- the run
@dataclass(frozen=True)
class Table1Options:
    """What a Table 1 run does (``recipes/table1.py``'s options), checked when made, before any work.

    Attributes:
        rows: row names (:data:`ROW_BY_NAME`), in table order as given.
        seeds: training seeds.
        sets: evaluation sets (:data:`SETS`).
        overrides: ``key=value`` overrides for every training run (never ``seed=``: see ``seeds``).
        quick: smoke run: :data:`QUICK_EPISODES` episodes per set, ``bc_quick`` training, all under :data:`QUICK_DIR`.
        from_checkpoints: train nothing: score the checkpoints there are (finished runs are still copied and shipped).
        checkpoints: the checkpoint directory; ``None``: ``checkpoints/`` (quick: under :data:`QUICK_DIR`).
        eval_dir: the per-episode cache; ``None``: ``results/eval/table1/`` (quick: under :data:`QUICK_DIR`).
        out: where ``table1.{json,md,png}`` go; ``None``: ``results/`` for the whole table, :data:`PART_DIR` for a
            part of it (:attr:`part`), under :data:`QUICK_DIR` with ``quick``.
        num_resamples: bootstrap resamples.
        eval_sets: (made from the others) the evaluation configs of :data:`SETS` (:func:`eval_sets`).

    Raises:
        ValueError: a bad option, naming it (``num_resamples`` below 1, a ``seed=`` override, an
            override the configs refuse).

    Examples:
        >>> options = Table1Options(rows=("open_loop",), quick=True)
        >>> options.checkpoints.as_posix(), options.eval_dir.as_posix(), options.out.as_posix()
        ('runs/table1_quick/checkpoints', 'runs/table1_quick/eval', 'runs/table1_quick/results')
        >>> Table1Options(rows=("spf-s0.8",), seeds=(2,), from_checkpoints=True).out.as_posix()  # a part
        'runs/table1_part'
        >>> Table1Options(overrides=("seed=3",))
        Traceback (most recent call last):
        ...
        ValueError: the override seed=... is not allowed: choose the training seeds with --seeds (e.g. --seeds 0,1,2)
    """

    rows: tuple[str, ...] = tuple(ROW_BY_NAME)
    seeds: tuple[int, ...] = DEFAULT_SEEDS
    sets: tuple[str, ...] = SETS
    overrides: tuple[str, ...] = ()
    quick: bool = False
    from_checkpoints: bool = False
    checkpoints: Path | None = None
    eval_dir: Path | None = None
    out: Path | None = None
    num_resamples: int = 10_000
    eval_sets: dict = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        def put(name: str, value) -> None:
            object.__setattr__(self, name, value)

        for name in ("rows", "seeds", "sets", "overrides"):
            put(name, tuple(getattr(self, name)))
        if self.num_resamples < 1:
            raise ValueError(f"argument --num-resamples: must be >= 1, got {self.num_resamples}")
        if any(item.split("=", 1)[0] == "seed" for item in self.overrides):
            raise ValueError("the override seed=... is not allowed: choose the training seeds with --seeds (e.g. --seeds 0,1,2)")
        root = QUICK_DIR if self.quick else Path(".")
        put("checkpoints", Path(self.checkpoints) if self.checkpoints else root / "checkpoints")
        put("eval_dir", Path(self.eval_dir) if self.eval_dir else (root / "eval" if self.quick else Path("results/eval/table1")))
        default_out = root / "results" if self.quick else (PART_DIR if self.part else Path("results"))
        put("out", Path(self.out) if self.out else default_out)
        try:  # bad overrides are refused here, before any work
            put("eval_sets", eval_sets(list(self.overrides), self.quick))
            for row in (ROW_BY_NAME[name] for name in self.rows if ROW_BY_NAME[name].trained):
                row_config(row, self.seeds[0], list(self.overrides), self.quick)
                if not self.quick:
                    dagger_config(row, self.seeds[0], self.overrides)
        except ValueError as err:
            raise ValueError(f"overrides: {err}") from err

    @property
    def part(self) -> bool:
        """Whether this run covers a part of the table: fewer rows, seeds or sets than the defaults."""
        return (
            set(self.rows) != set(ROW_BY_NAME) or not set(DEFAULT_SEEDS) <= set(self.seeds) or set(self.sets) != set(SETS)
        )


def reproduce(options: Table1Options) -> dict:
    """Train what is missing (unless ``options.from_checkpoints``), copy and ship finished runs, score every
    checkpoint on the sets (cached per episode), and write ``table1.{json,md,png}`` to ``options.out``.

    Returns:
        The table (:func:`spf_rl.eval.table1.build_table`), with ``shipped`` (line -> the seed shipped and
        its validation scores), ``budget`` (:func:`budgets`; ``bc_quick`` with ``--quick``) and each line's
        ``trained_on`` (seed -> the CPU model of this recipe's run: :func:`trained_on`); each line's ``pointer_pace`` (seed ->
        its checkpoint's pointer pace) and the table's ``pointer_pace`` (what it was measured on): :func:`pointer_paces`.
    """
    from spf_rl.device import resolve_device
    from spf_rl.train.bc import BCConfig

    overrides, seeds = list(options.overrides), list(options.seeds)
    base = load_config(BCConfig, "bc", overrides, preset=TABLE1_PRESET)
    device = str(resolve_device(base.device))
    rows = [ROW_BY_NAME[name] for name in options.rows]
    shipped = train_missing(rows, seeds, overrides, options.checkpoints, options.quick, train=not options.from_checkpoints)
    sets = {name: options.eval_sets[name] for name in options.sets}
    lines = table_lines(rows, base.data.episodes.demo_length, base.data.episodes.image_size)
    evaluations, missing = evaluate_all(lines, seeds, sets, options.checkpoints, options.eval_dir, device)
    table = build_table(lines, evaluations, sets, seeds, CLAIMS, missing, options.num_resamples)
    paces, table["pointer_pace"] = pointer_paces(lines, seeds, options.checkpoints, overrides, options.quick, device)
    table["shipped"] = shipped
    table["budget"] = {"preset": "bc_quick"} if options.quick else budgets(overrides)
    sources = trained_on(lines, seeds, options.checkpoints, options.quick)
    for row in table["rows"]:
        row["trained_on"] = sources.get(row["checkpoint_stem"], {})
        row["pointer_pace"] = paces.get(row["checkpoint_stem"], {})
        restarts = {str(seed): found for seed in sources.get(row["checkpoint_stem"], {})
                    if (found := run_restarts(row["checkpoint_stem"], seed, options.quick))}
        if restarts:  # only where the pointer-collapse guard restarted a run (the table is unchanged otherwise)
            row["pointer_restarts"] = restarts
    write_reports(table, options.out)
    logger.info("wrote %s/table1.{json,md,png}%s", options.out.as_posix(),
                " (a part of the table: rows, seeds or sets left out)" if options.part else "")
    return table

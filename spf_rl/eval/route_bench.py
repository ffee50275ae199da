"""The route benchmark: how well each policy follows routes of each style and length
(``recipes/route_bench.py`` is the command line).

Every model (shipped checkpoints by name, or ``.pt`` paths) and open-loop replay
(:class:`~spf_rl.modules.open_loop.OpenLoopPolicy`, the floor: it replays the
demonstrated actions blind) play the episodes of every *cell*: an episode set
(:data:`SETS`: the test split, and the test split on :data:`EXTENDED_HOUSES` houses) x a
route style (:data:`~envs.route_styles.ROUTE_STYLES`) x a length bucket (routes of
``lo`` to ``hi`` steps). A cell's episodes are those of one
:class:`~spf_rl.evaluation.EvalConfig` (``demo_length=hi``, shorter routes padded
and played at their own length; each route's own step limit ``ceil(5/3 n)``), so every
model plays the same episodes and comparisons are paired by episode. A policy built for
another demonstration length runs as a view at ``hi`` steps sharing its weights
(:func:`~spf_rl.modules.views.policy_for_length`); a random-sparsity model runs at one
sparsity (its config's by default).

Per cell and model: mean success, SPL, nDTW and SDTW with house-level bootstrap intervals
(:func:`~spf_rl.stats.hierarchical_bootstrap_ci`), and the paired difference from open-loop
replay on the same episodes in success and nDTW (:func:`~spf_rl.stats.paired_bootstrap`).
Training seeds of one recipe (labels that differ only in a ``-seed<N>`` suffix) are also
reported pooled over seeds, as one more column (:func:`seed_groups`, :func:`pooled_stats`).

* :class:`BenchOptions`: what a run does, checked when made (a ``ValueError`` naming the option);
* :func:`parse_buckets`, :func:`parse_list`: the command line's comma-separated values;
* :func:`run_bench`: evaluate what is missing (the JSON is written after every evaluation, and
  a rerun with the same set-up skips what it holds: an interrupted run resumes), then the
  table and the figure;
* :func:`cell_stats`, :func:`paired_against`: the statistics of a cell; :func:`by_style` (means per style), :func:`format_table`, :func:`format_by_model`
  (markdown) and :func:`plot_bench` (success by bucket, a panel per set and style).
"""
from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from envs.atomic_io import atomic_write_json
from envs.route_styles import ROUTE_STYLES
from envs.transforms import DEFAULT_NOISE
from spf_rl.eval.by_length import label_of
from spf_rl.evaluation import TEST_SEED
from spf_rl.records_cache import changed_fields, episodes_key, to_columns
from spf_rl.stats import DEFAULT_CONFIDENCE, DEFAULT_NUM_RESAMPLES, hierarchical_bootstrap_ci, paired_bootstrap

logger = logging.getLogger(__name__)

RECIPE = "recipes/route_bench.py"
#: The floor every model is compared with: open-loop replay of the demonstrated actions.
OPEN_LOOP = "open_loop"
#: Episode sets: name -> houses of the test split (``None``: the split's own).
EXTENDED_HOUSES = 100
SETS: dict[str, int | None] = {"test": None, "extended": EXTENDED_HOUSES}
STYLES = tuple(ROUTE_STYLES)
#: Length buckets, steps (inclusive).
DEFAULT_BUCKETS = ((10, 30), (31, 60), (61, 100))
#: Shipped names left out by default (see :func:`default_models`).
EXCLUDED_PREFIXES = ("homing-", "ppo-")
#: ``--quick``: a smoke run.
QUICK_MODELS = ("spf-s0.8", "rpf_original-s1")
QUICK_EPISODES = 8
#: Episodes per cell of the full run.
DEFAULT_EPISODES = 128
QUICK_BUCKETS = ((10, 30), (31, 60))
QUICK_SETS = ("test",)
#: A world of the condition axis (``--conditions``): the mismatched-memory cell, every episode shown
#: another route's frames with its own actions (``memory_mismatch=1``; open-loop replay is its floor).
MISMATCH = "mismatch"
DEFAULT_OUT = Path("results/route_bench.json")
QUICK_OUT = Path("results/route_bench_quick.json")
#: Per-episode scores reported (mean and interval), and those compared with open-loop replay.
BENCH_METRICS = ("success", "spl", "ndtw", "sdtw")
BENCH_PAIRED_METRICS = ("success", "ndtw")
#: Per-episode fields kept per model (columns), and per cell (the episodes, the same for every model).
BENCH_RECORD_FIELDS = ("success", "success_lab", "spl", "ndtw", "sdtw", "path_length_ratio", "wall_hits", "steps",
               "goal_distance", "path_length", "shortest_path_length")
EPISODE_KEYS = ("episode_index", "episode_seed", "house_seed", "demo_steps")
#: A label of one training seed of a recipe (see :func:`seed_groups`).
SEED_SUFFIX = re.compile(r"(?P<base>.+)-seed(?P<seed>\d+)")
#: Paired differences with a two-sided p-value below this are marked in the table.
ALPHA = 0.05
STATISTICS = (
    "mean over the cell's episodes; ci: 95% percentile bootstrap resampling houses, then episodes within each "
    "drawn house (spf_rl.stats.hierarchical_bootstrap_ci). vs_open_loop: paired bootstrap of mean(model) - "
    "mean(open_loop) on the same episodes, the same resamples for both (spf_rl.stats.paired_bootstrap); "
    "p_greater: fraction of resamples with a difference <= 0; p_two_sided: twice the smaller tail. "
    "A seed group ('<base> (<n> seeds)': models whose labels differ only in -seed<N>) is pooled: means over seeds "
    "and episodes, each episode's scores averaged over the seeds before resampling (spf_rl.eval.route_bench.pooled_stats). "
    "vs_reference (with --reference): per world, the same paired bootstrap of mean(model) - mean(reference)."
)


# ------------------------------------------------------------------------ parsing
def parse_list(text: str, allowed: Sequence[str] | None, option: str) -> tuple[str, ...]:
    """Comma-separated names (repeats dropped, order kept), each one of ``allowed`` (any, if ``None``).

    Raises:
        ValueError: none, or an unknown name; the message names ``option``.

    Examples:
        >>> parse_list("tour, planner,tour", STYLES, "--styles")
        ('tour', 'planner')
        >>> parse_list("tour,zigzag", STYLES, "--styles")
        Traceback (most recent call last):
        ...
        ValueError: argument --styles: unknown ['zigzag']; allowed: planner, tour, driven
    """
    items = tuple(dict.fromkeys(item.strip() for item in str(text).split(",") if item.strip()))
    unknown = [item for item in items if allowed is not None and item not in allowed]
    if unknown or not items:
        allowed_text = f"; allowed: {', '.join(allowed)}" if allowed is not None else ""
        raise ValueError(f"argument {option}: {'unknown ' + str(unknown) if unknown else 'no names in ' + repr(text)}{allowed_text}")
    return items


def parse_world(text: str | None) -> str | None:
    """A world of the condition axis: ``None`` (or ``"none"``) for the teaching world, :data:`MISMATCH`,
    or repeat conditions (:func:`~envs.conditions.parse_conditions`: ``"light@0.5"``, a mixture), in
    their one spelling.

    Raises:
        ValueError: bad conditions, naming ``--conditions``.

    Examples:
        >>> parse_world("none"), parse_world("mismatch"), parse_world("light@.5")
        (None, 'mismatch', 'light@0.5=1.0')
        >>> parse_world("fog@1")
        Traceback (most recent call last):
        ...
        ValueError: argument --conditions: conditions: unknown condition 'fog'; allowed names are none, light, paint, furniture, camera, sensor (or mismatch).
    """
    from envs.conditions import parse_conditions

    if text is None or str(text).strip() == "none":
        return None
    if str(text).strip() == MISMATCH:
        return MISMATCH
    try:
        return parse_conditions(str(text)).spec
    except ValueError as err:
        raise ValueError(f"argument --conditions: {str(err).rstrip('.')} (or {MISMATCH}).") from None


def check_buckets(buckets: Sequence[Sequence[int]]) -> tuple[tuple[int, int], ...]:
    """``buckets`` as sorted ``(lo, hi)`` pairs of steps, checked: ``10 <= lo <= hi <= 100``, no overlaps.

    Raises:
        ValueError: a bad or overlapping bucket, naming ``--buckets``.

    Examples:
        >>> check_buckets([(31, 60), (10, 30)])
        ((10, 30), (31, 60))
        >>> check_buckets([(10, 40), (31, 60)])
        Traceback (most recent call last):
        ...
        ValueError: argument --buckets: buckets 10-40 and 31-60 overlap
    """
    from envs.route_styles import MAX_STYLE_LENGTH, MIN_STYLE_LENGTH

    pairs = []
    for bucket in buckets:
        try:
            lo, hi = (int(x) for x in bucket)
        except (TypeError, ValueError):
            raise ValueError(f"argument --buckets: a bucket is (shortest, longest) steps, got {bucket!r}") from None
        if not MIN_STYLE_LENGTH <= lo <= hi <= MAX_STYLE_LENGTH:
            raise ValueError(
                f"argument --buckets: a bucket lo-hi needs {MIN_STYLE_LENGTH} <= lo <= hi <= {MAX_STYLE_LENGTH} steps, got {lo}-{hi}"
            )
        pairs.append((lo, hi))
    if not pairs:
        raise ValueError("argument --buckets: no buckets")
    pairs.sort()
    for (lo_a, hi_a), (lo_b, hi_b) in zip(pairs, pairs[1:]):
        if lo_b <= hi_a:
            raise ValueError(f"argument --buckets: buckets {lo_a}-{hi_a} and {lo_b}-{hi_b} overlap")
    return tuple(pairs)


def parse_buckets(text: str) -> tuple[tuple[int, int], ...]:
    """Length buckets from ``"lo-hi,lo-hi,..."`` (steps, inclusive; ``"n"`` alone is ``n-n``), sorted.

    Raises:
        ValueError: not of that form, or a bad bucket (:func:`check_buckets`), naming ``--buckets``.

    Examples:
        >>> parse_buckets("31-60, 10-30")
        ((10, 30), (31, 60))
        >>> parse_buckets("10-30,61")
        ((10, 30), (61, 61))
        >>> parse_buckets("5-30")
        Traceback (most recent call last):
        ...
        ValueError: argument --buckets: a bucket lo-hi needs 10 <= lo <= hi <= 100 steps, got 5-30
        >>> parse_buckets("10..30")
        Traceback (most recent call last):
        ...
        ValueError: argument --buckets: '10..30' is not lo-hi (steps, e.g. 10-30,31-60)
    """
    buckets = []
    for item in (item.strip() for item in str(text).split(",") if item.strip()):
        match = re.fullmatch(r"(\d+)(?:\s*-\s*(\d+))?", item)
        if match is None:
            raise ValueError(f"argument --buckets: {item!r} is not lo-hi (steps, e.g. 10-30,31-60)")
        buckets.append((int(match[1]), int(match[2] or match[1])))
    return check_buckets(buckets)


def bucket_name(bucket: Sequence[int]) -> str:
    """``"lo-hi"``.

    Examples:
        >>> bucket_name((10, 30))
        '10-30'
    """
    return f"{bucket[0]}-{bucket[1]}"


def default_models() -> tuple[str, ...]:
    """Every shipped checkpoint but ``homing-*`` (trained to return to a route's start, not to
    follow it) and ``ppo-*`` (trained and scored under the older ``paper_symmetric`` noise):
    both can still be named with ``--models``."""
    from spf_rl.hub import list_checkpoints

    return tuple(name for name in list_checkpoints() if not name.startswith(EXCLUDED_PREFIXES))


def check_models(models: Sequence[str]) -> tuple[str, ...]:
    """Shipped names, existing ``.pt`` paths or export directories (``open_loop`` is dropped: it always plays).

    Raises:
        ValueError: an unknown name or missing file (naming ``--models``), or two with one label.
    """
    from spf_rl.hub import list_checkpoints
    from spf_rl.modules.exported import is_export

    shipped = list_checkpoints()
    models = tuple(dict.fromkeys(str(m) for m in models if str(m) != OPEN_LOOP))
    unknown = [m for m in models if m not in shipped and not (m.endswith(".pt") and Path(m).is_file()) and not is_export(m)]
    if unknown:
        raise ValueError(f"argument --models: unknown {unknown} (shipped names, .pt files or export directories); "
                         f"shipped: {', '.join(shipped)}")
    labels = [label_of(m) for m in models]
    if len(set(labels)) != len(labels) or OPEN_LOOP in labels:
        raise ValueError(f"argument --models: two models would have one label: {labels}")
    return models


# ------------------------------------------------------------------------ options
@dataclass(frozen=True)
class BenchOptions:
    """What a route benchmark does (``recipes/route_bench.py``'s options), checked when made.

    ``None`` fields take the full run's default, or with ``quick`` the smoke run's.

    Attributes:
        models: shipped names or ``.pt`` paths (default :func:`default_models`; quick :data:`QUICK_MODELS`);
            open-loop replay always plays.
        styles: route styles (:data:`STYLES`).
        buckets: length buckets ``(lo, hi)``, steps (default :data:`DEFAULT_BUCKETS`; quick :data:`QUICK_BUCKETS`).
        sets: episode sets (:data:`SETS`; quick: the test set).
        episodes: episodes per cell (default :data:`DEFAULT_EPISODES`; quick :data:`QUICK_EPISODES`).
        seed: seed of the episodes (:data:`~spf_rl.evaluation.TEST_SEED`, that of the other evaluations).
        noise: actuation-noise preset.
        out: the JSON (the figure and the markdown table go next to it, ``.png`` and ``.md``);
            default :data:`DEFAULT_OUT` (quick :data:`QUICK_OUT`).
        quick: the smoke run's defaults.
        device: where the policies run.
        random_sparsity: the sparsity random-sparsity models run at (``None``: each one's config sparsity).
        num_resamples: bootstrap resamples.
        test_houses: houses of the ``test`` set (``None``: the split's; fewer for smoke tests).
        image_size: frame side, pixels (every model's must be this).
        num_agents: agents stepped together.
        num_collectors: processes playing a cell's episodes (how, never which: the same episodes and scores).
        store_root: where episode stores go (``None``: :func:`~spf_rl.evaluation.episode_store_root`).
        progress: progress bars.
        conditions: the worlds the routes are repeated in (:func:`parse_world`): ``None`` the teaching
            world (the default, alone), repeat conditions, or :data:`MISMATCH`; a cell per world x set x
            style x bucket, on the same routes.
        reference: a model every other is paired with per world (:func:`by_world`'s ``vs_reference``): one
            of ``models`` as given or by its label, or a seed group's label (:func:`seed_groups`); ``None``: none.

    Raises:
        ValueError: a bad option, naming it (``argument --episodes: ...``).

    Examples:
        >>> options = BenchOptions(models=("spf-s0.8",), quick=True)
        >>> options.episodes, options.sets, options.buckets, options.out.as_posix()
        (8, ('test',), ((10, 30), (31, 60)), 'results/route_bench_quick.json')
        >>> BenchOptions(models=("spf-s0.8",), episodes=0)
        Traceback (most recent call last):
        ...
        ValueError: argument --episodes: must be a positive int, got 0
        >>> BenchOptions(models=("spf-s0.8", "rpf_original-s1"), reference="spf-s0.8").reference
        'spf-s0.8'
        >>> BenchOptions(models=("spf-s0.8",), reference="spf-s0.6")
        Traceback (most recent call last):
        ...
        ValueError: argument --reference: 'spf-s0.6' is not a model of this run; allowed: spf-s0.8
    """

    models: tuple[str, ...] | None = None
    styles: tuple[str, ...] = STYLES
    buckets: tuple[tuple[int, int], ...] | None = None
    sets: tuple[str, ...] | None = None
    episodes: int | None = None
    seed: int = TEST_SEED
    noise: str = DEFAULT_NOISE
    out: Path | None = None
    quick: bool = False
    device: str = "cpu"
    random_sparsity: float | None = None
    num_resamples: int = DEFAULT_NUM_RESAMPLES
    test_houses: int | None = None
    image_size: int = 64
    num_agents: int = 25
    num_collectors: int = 1
    store_root: str | None = None
    progress: bool = False
    conditions: tuple[str | None, ...] = (None,)
    reference: str | None = None
    set_houses: dict = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        def put(name: str, value) -> None:
            object.__setattr__(self, name, value)

        def positive(name: str, option: str) -> None:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"argument {option}: must be a positive int, got {value!r}")

        quick = self.quick
        put("models", check_models(self.models if self.models is not None else (QUICK_MODELS if quick else default_models())))
        put("styles", parse_list(",".join(self.styles), STYLES, "--styles"))
        put("buckets", check_buckets(self.buckets if self.buckets is not None else (QUICK_BUCKETS if quick else DEFAULT_BUCKETS)))
        put("sets", parse_list(",".join(self.sets if self.sets is not None else (QUICK_SETS if quick else SETS)), tuple(SETS), "--sets"))
        put("episodes", self.episodes if self.episodes is not None else (QUICK_EPISODES if quick else DEFAULT_EPISODES))
        put("out", Path(self.out) if self.out is not None else (QUICK_OUT if quick else DEFAULT_OUT))
        for name, option in (("episodes", "--episodes"), ("num_resamples", "--num-resamples"), ("image_size", "image_size"),
                             ("num_agents", "num_agents"), ("num_collectors", "--num-collectors")):
            positive(name, option)
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ValueError(f"argument --seed: must be an int >= 0, got {self.seed!r}")
        if self.test_houses is not None:
            positive("test_houses", "test_houses")
        from envs.transforms import NOISE_PRESETS

        if self.noise not in NOISE_PRESETS:
            raise ValueError(f"argument --noise: unknown {self.noise!r}; allowed: {', '.join(sorted(NOISE_PRESETS))}")
        if self.random_sparsity is not None and not 0.0 < float(self.random_sparsity) <= 1.0:
            raise ValueError(f"argument --random-sparsity: must be in (0, 1], got {self.random_sparsity!r}")
        from spf_rl.device import check_device

        try:
            check_device(self.device)
        except ValueError as err:
            raise ValueError(f"argument --device: {err}") from err
        worlds = tuple(dict.fromkeys(parse_world(world) for world in self.conditions))
        if not worlds:
            raise ValueError("argument --conditions: no worlds")
        put("conditions", worlds)
        if self.reference is not None:
            put("reference", check_reference(str(self.reference), self.models))
        houses = {**SETS, "test": self.test_houses}
        put("set_houses", {name: houses[name] for name in self.sets})


# -------------------------------------------------------------------------- cells
def cell_key(set_name: str, style: str, bucket: Sequence[int], world: str | None = None) -> str:
    """The key of a cell in the JSON: ``"<set>/<style>/<lo>-<hi>"``, then ``"/<world>"`` in a changed world.

    Examples:
        >>> cell_key("test", "tour", (10, 30)), cell_key("test", "tour", (10, 30), "light@1.0=1.0")
        ('test/tour/10-30', 'test/tour/10-30/light@1.0=1.0')
    """
    return f"{set_name}/{style}/{bucket_name(bucket)}" + ("" if world is None else f"/{world}")


def cell_config(options: BenchOptions, set_name: str, style: str, bucket: Sequence[int], world: str | None = None):
    """The :class:`~spf_rl.evaluation.EvalConfig` of a cell: routes of ``style`` and ``bucket``
    lengths padded to the longest, each with its own step limit, repeated in ``world``
    (:func:`parse_world`; the routes and their stored demonstrations are the same in every world)."""
    from envs.episode_spec import EpisodeSpec
    from spf_rl.evaluation import EvalConfig, episode_store_root

    episodes = EpisodeSpec(
        split="test", num_houses=options.set_houses[set_name], seed=options.seed, noise=options.noise,
        demo_length=bucket[1], max_steps=None, route_style=style, route_lengths=tuple(bucket), image_size=options.image_size,
        conditions=None if world in (None, MISMATCH) else world, memory_mismatch=1.0 if world == MISMATCH else None,
    )
    return EvalConfig(
        episodes, num_episodes=options.episodes, num_agents=options.num_agents, num_collectors=options.num_collectors,
        store_root=options.store_root if options.store_root is not None else episode_store_root(),
    )


@dataclass
class BenchModel:
    """A model of the benchmark: its label, policy (``None`` for open-loop replay, made per cell), the
    sparsity a random-sparsity model reads its memory at (``None``: the model's own) and what the JSON
    says of it.

    Its records in a cell are keyed by the :func:`~spf_rl.records_cache.policy_sha256` of its view at the
    cell's demonstration length (:meth:`policy_sha256`), the cell by the episodes'
    :func:`~spf_rl.records_cache.episodes_key`.

    Examples:
        >>> replay = BenchModel(OPEN_LOOP, None, None, {"checkpoint": None})
        >>> type(replay.at_length(40)).__name__, replay.policy_sha256(40)
        ('OpenLoopPolicy', None)
    """

    label: str
    policy: object | None
    sparsity: float | None
    info: dict
    views: dict = field(default_factory=dict)

    def at_length(self, demo_length: int):
        """The policy for demonstrations of ``demo_length`` steps (open-loop replay reads any length)."""
        from spf_rl.modules import OpenLoopPolicy
        from spf_rl.modules.views import policy_for_length

        if self.policy is None:
            return OpenLoopPolicy()
        if demo_length not in self.views:
            view = policy_for_length(self.policy, demo_length)
            if self.sparsity is not None:  # set_sparsity is not part of the weights: set it on the view
                view.set_sparsity(self.sparsity)
            self.views[demo_length] = view
        return self.views[demo_length]

    def policy_sha256(self, demo_length: int) -> str | None:
        """The key of this model's records on a cell of ``demo_length``-step demonstrations."""
        from spf_rl.records_cache import policy_sha256

        return policy_sha256(self.at_length(demo_length))


def shown_path(path: str | Path) -> str:
    """``path`` as the results show it: relative to the working directory when it lies under it (so a
    shipped checkpoint resolved from its name reads ``checkpoints/...`` on every machine), else as given.

    Examples:
        >>> shown_path(Path.cwd() / "checkpoints" / "x.pt")
        'checkpoints/x.pt'
        >>> shown_path("/elsewhere/x.pt")
        '/elsewhere/x.pt'
    """
    try:
        return Path(path).resolve().relative_to(Path.cwd().resolve()).as_posix()
    except ValueError:
        return str(path)


def load_models(options: BenchOptions) -> list[BenchModel]:
    """Open-loop replay, then every model of ``options`` loaded on its device.

    Raises:
        ValueError: a model whose frames are not ``options.image_size`` pixels.
    """
    from spf_rl.hub import checked_checkpoint, load_policy, policy_from_checkpoint
    from spf_rl.modules.exported import is_export

    models = [BenchModel(OPEN_LOOP, None, None, {"checkpoint": None, "model_type": OPEN_LOOP})]
    for name in options.models:
        if is_export(name):  # an export directory, run by ONNX Runtime (recipes/export.py)
            path, policy = name, load_policy(name).policy
            payload = {"model_type": policy.model_type}
        else:
            path = checked_checkpoint(name)
            policy, payload = policy_from_checkpoint(path, device=options.device)
        config = policy.config
        if tuple(config.image_size) != (options.image_size, options.image_size):
            raise ValueError(f"{name} sees {tuple(config.image_size)} frames, the benchmark renders {options.image_size} px")
        random = getattr(config, "sparsity_range", None) is not None
        own = float(policy.sparsity) if is_export(name) else float(config.sparsity)  # an export keeps its own
        sparsity = (float(options.random_sparsity) if options.random_sparsity is not None else own) if random else None
        info = {"checkpoint": shown_path(path), "model_type": payload["model_type"], "demo_length": config.demo_length,
                "sparsity": float(config.sparsity), "sparsity_range": list(config.sparsity_range) if random else None,
                "played_at_sparsity": sparsity}
        models.append(BenchModel(label_of(name), policy, sparsity, info))
    return models


def evaluate_model(model: BenchModel, config, progress: bool = False) -> list[dict]:
    """Per-episode records of one model on a cell's episodes (open-loop replay without rendering: the same episodes)."""
    import dataclasses

    from spf_rl import evaluation

    if model.policy is None:
        config = dataclasses.replace(config, render=False)
    return evaluation.evaluate_policy(model.at_length(config.episodes.demo_length), config, progress=progress)[1]


# --------------------------------------------------------------------- statistics
def paired_against(a: dict, b: dict, houses: Sequence, num_resamples: int, metrics: Sequence[str] = BENCH_PAIRED_METRICS) -> dict:
    """Paired bootstrap of ``a`` - ``b`` (per-episode columns ``{metric: values}`` of the same episodes) per metric.

    Returns:
        ``{metric: {"difference", "ci", "p_greater", "p_two_sided"}}``.

    Examples:
        >>> a = {"success": [1, 0, 1, 1], "ndtw": [0.9, 0.2, 0.8, 0.7]}
        >>> paired_against(a, a, [0, 0, 1, 1], num_resamples=100)["success"]
        {'difference': 0.0, 'ci': [0.0, 0.0], 'p_greater': 1.0, 'p_two_sided': 1.0}
    """
    out = {}
    for metric in metrics:
        result = paired_bootstrap(np.asarray(a[metric], dtype=float), np.asarray(b[metric], dtype=float), np.asarray(houses),
                                  DEFAULT_CONFIDENCE, num_resamples)
        out[metric] = {"difference": result.difference, "ci": list(result.ci), "p_greater": result.p_greater,
                       "p_two_sided": result.p_two_sided}
    return out


def cell_stats(cell: dict, num_resamples: int) -> dict:
    """Per model of a complete cell: the mean and house-level interval of each of :data:`BENCH_METRICS`,
    and (models other than open-loop replay) ``vs_open_loop``: :func:`paired_against` open-loop replay."""
    stats = {label: _scores(cell, [label], num_resamples, paired=label != OPEN_LOOP) for label in cell["models"]}
    for group, members in seed_groups(list(cell["models"])).items():
        stats[group] = pooled_stats(cell, members, num_resamples)
    return stats


def seed_groups(labels: Sequence[str]) -> dict[str, list[str]]:
    """Models that are training seeds of one recipe: labels that differ only in a ``-seed<N>`` suffix,
    two or more of them, as ``{"<base> (<n> seeds)": [labels in seed order]}``.

    Examples:
        >>> seed_groups(["open_loop", "routes/a-seed1", "routes/a-seed0", "routes/b-seed0", "spf-s0.8"])
        {'routes/a (2 seeds)': ['routes/a-seed0', 'routes/a-seed1']}
    """
    groups: dict[str, list[tuple[int, str]]] = {}
    for label in labels:
        match = SEED_SUFFIX.fullmatch(label)
        if match is not None:
            groups.setdefault(match["base"], []).append((int(match["seed"]), label))
    return {f"{base} ({len(members)} seeds)": [label for _, label in sorted(members)]
            for base, members in groups.items() if len(members) >= 2}


def pooled_stats(cell: dict, members: Sequence[str], num_resamples: int) -> dict:
    """The statistics of :func:`cell_stats` for training seeds ``members`` of one recipe, pooled: each
    metric's mean over seeds and episodes, its house-level interval, and the paired difference from
    open-loop replay pooled over seeds (every seed played the cell's episodes; resamples draw houses, then
    episodes, and take every seed's score of a drawn episode). ``per_seed`` gives each seed's mean.

    Examples:
        >>> cell = {"episodes": {"house_seed": [0, 0, 1, 1]}, "models": {
        ...     "open_loop": {"columns": {"success": [0, 0, 1, 0], "spl": [0, 0, 1, 0], "ndtw": [0.2] * 4, "sdtw": [0] * 4}},
        ...     "m-seed0": {"columns": {"success": [1, 1, 1, 0], "spl": [1, 1, 1, 0], "ndtw": [0.8] * 4, "sdtw": [0] * 4}},
        ...     "m-seed1": {"columns": {"success": [1, 0, 1, 1], "spl": [1, 0, 1, 1], "ndtw": [0.6] * 4, "sdtw": [0] * 4}}}}
        >>> row = pooled_stats(cell, ["m-seed0", "m-seed1"], num_resamples=200)
        >>> row["success"]["mean"], row["per_seed"]["success"], round(row["vs_open_loop"]["ndtw"]["difference"], 6)
        (0.75, [0.75, 0.75], 0.5)
    """
    row = _scores(cell, members, num_resamples, paired=True)
    row["seeds"] = list(members)
    row["per_seed"] = {metric: [float(v) for v in np.asarray([cell["models"][m]["columns"][metric] for m in members],
                                                               dtype=float).mean(axis=1)] for metric in BENCH_METRICS}
    return row


def _scores(cell: dict, members: Sequence[str], num_resamples: int, paired: bool) -> dict:
    """Means over ``members``' seeds and the cell's episodes, house-level intervals and (``paired``) the
    difference from open-loop replay: one model is one member."""
    houses = np.asarray(cell["episodes"]["house_seed"])
    columns = {metric: np.asarray([cell["models"][m]["columns"][metric] for m in members], dtype=float) for metric in BENCH_METRICS}
    row = {"episodes": int(houses.size), "houses": int(np.unique(houses).size)}
    for metric, values in columns.items():
        row[metric] = {"mean": float(values.mean()),
                       "ci": list(hierarchical_bootstrap_ci(values.mean(axis=0), houses, DEFAULT_CONFIDENCE, num_resamples))}
    if paired:
        row["vs_open_loop"] = paired_against(columns, cell["models"][OPEN_LOOP]["columns"], houses, num_resamples)
    return row


# ------------------------------------------------------------------------ reports
def report_labels(setup: dict) -> list[str]:
    """The columns of the table and the lines of the figure: every model, then every seed group."""
    return list(setup["models"]) + list(setup.get("seed_groups", {}))


def format_table(content: dict) -> str:
    """The markdown table of a benchmark's JSON content: a row per set x style x bucket, a column per
    model, ``success / nDTW`` (``*``: paired difference from open-loop replay with two-sided p < 0.05).

    Examples:
        >>> def model(success, ndtw, p=None):
        ...     row = {"success": {"mean": success}, "ndtw": {"mean": ndtw}}
        ...     if p is not None:
        ...         row["vs_open_loop"] = {"success": {"p_two_sided": p}, "ndtw": {"p_two_sided": 0.5}}
        ...     return row
        >>> cells = {"test/tour/10-30": {"set": "test", "style": "tour", "bucket": [10, 30],
        ...          "stats": {"open_loop": model(0.25, 0.5), "spf-s0.8": model(0.75, 0.875, p=0.01)}}}
        >>> content = {"setup": {"episodes": 8, "models": {"open_loop": {}, "spf-s0.8": {}}}, "cells": cells}
        >>> print(format_table(content))
        | set | style | steps | open_loop | spf-s0.8 |
        |---|---|---|---|---|
        | test | tour | 10-30 | 0.25 / 0.50 | 0.75* / 0.88 |
        <BLANKLINE>
        success / nDTW, mean over 8 episodes per cell; * after a number: paired difference from open-loop replay on the same episodes, two-sided p < 0.05 (house-level bootstrap).
    """
    labels = report_labels(content["setup"])
    lines = ["| set | style | steps | " + " | ".join(labels) + " |", "|---" * (3 + len(labels)) + "|"]
    for cell in content["cells"].values():
        stats = cell.get("stats")
        if not stats:
            continue
        entries = []
        for label in labels:
            row = stats.get(label)
            if row is None:
                entries.append("-")
                continue
            paired = row.get("vs_open_loop", {})
            marks = {m: "*" if m in paired and paired[m]["p_two_sided"] < ALPHA else "" for m in BENCH_PAIRED_METRICS}
            entries.append(f"{row['success']['mean']:.2f}{marks['success']} / {row['ndtw']['mean']:.2f}{marks['ndtw']}")
        lines.append(f"| {cell['set']} | {_style_in(cell)} | {bucket_name(cell['bucket'])} | " + " | ".join(entries) + " |")
    lines += ["", f"success / nDTW, mean over {content['setup']['episodes']} episodes per cell; * after a number: paired "
              "difference from open-loop replay on the same episodes, two-sided p < 0.05 (house-level bootstrap)."]
    if content["setup"].get("seed_groups"):
        lines[-1] += " (n seeds): the seeds' columns pooled, means over seeds and episodes, paired tests pooled over seeds."
    return "\n".join(lines)


def world_label(world: str | None) -> str:
    """A world of the condition axis as tables name it: ``"none"`` for the teaching world,
    ``"light@0.5"`` for one condition, the mixture's spelling otherwise.

    Examples:
        >>> world_label(None), world_label("light@0.5=1.0"), world_label("mismatch")
        ('none', 'light@0.5', 'mismatch')
    """
    if world is None:
        return "none"
    return world[: -len("=1.0")] if world.count("=") == 1 and world.endswith("=1.0") else world


def _style_in(cell: dict) -> str:
    """A cell's style, after its world where that is not the teaching world."""
    world = cell.get("world")
    return cell["style"] if world is None else f"{world_label(world)}: {cell['style']}"


def by_style(content: dict) -> dict:
    """Each model's (and seed group's) means over all of a style's complete cells, per set:
    ``{set: {style: {label: {"success": x, "ndtw": x, "episodes": n}}}}``, every cell's episodes
    weighted alike (for a seed group, the mean over its seeds too).

    Examples:
        >>> def row(success, episodes=4):
        ...     return {"episodes": episodes, "success": {"mean": success}, "ndtw": {"mean": success / 2}}
        >>> cells = {f"test/tour/{b}": {"set": "test", "style": "tour", "bucket": [1, 2],
        ...          "stats": {"spf-s0.8": row(s, n)}} for b, s, n in (("a", 1.0, 4), ("b", 0.25, 12))}
        >>> by_style({"setup": {"models": {"spf-s0.8": {}}}, "cells": cells})
        {'test': {'tour': {'spf-s0.8': {'success': 0.4375, 'ndtw': 0.21875, 'episodes': 16}}}}
    """
    out: dict = {}
    for cell in content["cells"].values():
        for label, row in (cell.get("stats") or {}).items():
            into = out.setdefault(cell["set"], {}).setdefault(_style_in(cell), {}).setdefault(
                label, {"success": 0.0, "ndtw": 0.0, "episodes": 0})
            for metric in ("success", "ndtw"):
                into[metric] += row[metric]["mean"] * row["episodes"]
            into["episodes"] += row["episodes"]
    for styles in out.values():
        for labels in styles.values():
            for into in labels.values():
                for metric in ("success", "ndtw"):
                    into[metric] /= into["episodes"]
    return out


def format_by_model(content: dict) -> str:
    """Markdown tables of a benchmark's success, one per set: a row per model (and seed group), a column per
    style x bucket (``*``: paired difference from open-loop replay with two-sided p < 0.05). The layout that
    stays readable with many models; nDTW is in :func:`format_table`.

    Examples:
        >>> def model(success, p=None):
        ...     row = {"episodes": 8, "success": {"mean": success}, "ndtw": {"mean": 0.5}}
        ...     if p is not None:
        ...         row["vs_open_loop"] = {"success": {"p_two_sided": p}}
        ...     return row
        >>> cells = {f"test/{style}/{b}": {"set": "test", "style": style, "bucket": bucket,
        ...          "stats": {"open_loop": model(0.25), "spf-s0.8": model(success, p=0.01 if style == "tour" else 0.2)}}
        ...          for style in ("tour", "driven") for b, bucket, success in (("10-30", [10, 30], 0.75), ("31-60", [31, 60], 0.5))}
        >>> content = {"setup": {"episodes": 8, "models": {"open_loop": {}, "spf-s0.8": {}}}, "cells": cells}
        >>> print(format_by_model(content))
        **test** (success, mean over 8 episodes per cell; a style's column: over all of its lengths)
        <BLANKLINE>
        | model | tour 10-30 | tour 31-60 | driven 10-30 | driven 31-60 | tour | driven |
        |---|---|---|---|---|---|---|
        | open_loop | 0.25 | 0.25 | 0.25 | 0.25 | 0.250 | 0.250 |
        | spf-s0.8 | 0.75* | 0.50* | 0.75 | 0.50 | 0.625 | 0.625 |
        <BLANKLINE>
        * after a number: paired difference from open-loop replay on the same episodes, two-sided p < 0.05 (house-level bootstrap).
    """
    labels = report_labels(content["setup"])
    cells = [cell for cell in content["cells"].values() if cell.get("stats")]
    means = by_style(content)
    lines: list[str] = []
    for set_name in dict.fromkeys(cell["set"] for cell in cells):
        columns = [cell for cell in cells if cell["set"] == set_name]
        styles = means[set_name]
        lines += [f"**{set_name}** (success, mean over {content['setup']['episodes']} episodes per cell; "
                  "a style's column: over all of its lengths)", "",
                  "| model | " + " | ".join([f"{_style_in(c)} {bucket_name(c['bucket'])}" for c in columns] + list(styles)) + " |",
                  "|---" * (1 + len(columns) + len(styles)) + "|"]
        for label in labels:
            entries = []
            for cell in columns:
                row = cell["stats"].get(label)
                if row is None:
                    entries.append("-")
                    continue
                p = row.get("vs_open_loop", {}).get("success", {}).get("p_two_sided")
                entries.append(f"{row['success']['mean']:.2f}" + ("*" if p is not None and p < ALPHA else ""))
            entries += [f"{labels_[label]['success']:.3f}" if label in labels_ else "-" for labels_ in styles.values()]
            lines.append(f"| {label} | " + " | ".join(entries) + " |")
        lines.append("")
    lines.append("* after a number: paired difference from open-loop replay on the same episodes, two-sided p < 0.05 "
                 "(house-level bootstrap).")
    return "\n".join(lines)


def check_reference(reference: str, models: Sequence[str]) -> str:
    """The label of ``--reference``: one of ``models`` (as given or by label) or a seed group of them.

    Raises:
        ValueError: anything else, naming ``--reference`` and the allowed labels.

    Examples:
        >>> check_reference("runs/a/best.pt", ["runs/a/best.pt", "spf-s0.8"])
        'a/best'
        >>> check_reference("r/a (2 seeds)", ["r/a-seed0", "r/a-seed1"])
        'r/a (2 seeds)'
        >>> check_reference("./runs/a/best.pt", ["runs/a/best.pt"])  # the same file, spelt otherwise
        'a/best'
    """
    labels = {model: label_of(model) for model in models}
    if reference in labels:
        return labels[reference]
    if label_of(reference) in labels.values():  # the same file, spelt otherwise
        return label_of(reference)
    allowed = list(labels.values()) + list(seed_groups(list(labels.values())))
    if reference not in allowed:
        raise ValueError(f"argument --reference: {reference!r} is not a model of this run; allowed: {', '.join(allowed)}")
    return reference


def by_world(content: dict, num_resamples: int) -> dict:
    """Each model's (and seed group's) success and nDTW per world of the condition axis, pooled over
    the world's complete cells (styles x buckets) of a set, with house-level intervals and the paired
    difference from open-loop replay on the same episodes (a seed group: each episode's scores averaged
    over its seeds first): ``{set: {world: {label: {"success", "ndtw", "episodes", "vs_open_loop"}}}}``.
    With a ``reference`` in the set-up (``--reference``), every other model's row also has
    ``vs_reference``: the same paired difference from the reference (but a row that shares a seed with
    it: the reference's own seed group, or a member of the reference group).

    Examples:
        >>> cells = {"a": {"set": "test", "world": "light@1.0=1.0", "stats": {}, "episodes": {"house_seed": [0, 0, 1, 1]},
        ...   "models": {"open_loop": {"columns": {"success": [0, 0, 1, 0], "ndtw": [0.2] * 4}},
        ...              "m": {"columns": {"success": [1, 1, 1, 0], "ndtw": [0.8] * 4}}}}}
        >>> row = by_world({"setup": {"models": {"open_loop": {}, "m": {}}}, "cells": cells}, 200)["test"]["light@1.0"]["m"]
        >>> row["success"]["mean"], row["episodes"], row["vs_open_loop"]["success"]["difference"]
        (0.75, 4, 0.5)
    """
    setup = content["setup"]
    reference = setup.get("reference")
    groups_of = {label: set(members) for label, members in {**{label: [label] for label in setup["models"]},
                                                            **setup.get("seed_groups", {})}.items()}
    # a model is never paired with a reference that shares its seeds (a group with one of its own members)
    overlaps = groups_of.get(reference, {reference})
    groups = {label: [label] for label in setup["models"]}
    groups.update(setup.get("seed_groups", {}))
    pooled: dict = {}
    for cell in content["cells"].values():
        if cell.get("stats") is None:
            continue
        into = pooled.setdefault(cell["set"], {}).setdefault(world_label(cell.get("world")), {"houses": [], "columns": {}})
        into["houses"] += list(cell["episodes"]["house_seed"])
        for label, members in groups.items():
            if not all(m in cell["models"] for m in members):
                continue
            columns = into["columns"].setdefault(label, {"success": [], "ndtw": []})
            for metric in columns:
                values = np.asarray([cell["models"][m]["columns"][metric] for m in members], dtype=float).mean(axis=0)
                columns[metric] += values.tolist()
    out: dict = {}
    for set_name, worlds in pooled.items():
        for world, data in worlds.items():
            houses = np.asarray(data["houses"])
            floor = data["columns"].get(OPEN_LOOP)
            against = data["columns"].get(reference) if reference is not None else None
            if against is not None and len(against["success"]) != houses.size:
                against = None
            for label, columns in data["columns"].items():
                if len(columns["success"]) != houses.size:
                    continue  # a model missing from some of the world's cells
                row: dict = {"episodes": int(houses.size)}
                for metric, values in columns.items():
                    values = np.asarray(values)
                    row[metric] = {"mean": float(values.mean()),
                                   "ci": list(hierarchical_bootstrap_ci(values, houses, DEFAULT_CONFIDENCE, num_resamples))}
                if label != OPEN_LOOP and floor is not None:
                    row["vs_open_loop"] = paired_against(columns, floor, houses, num_resamples)
                if against is not None and label != OPEN_LOOP and not groups_of.get(label, {label}) & overlaps:
                    row["vs_reference"] = paired_against(columns, against, houses, num_resamples)
                out.setdefault(set_name, {}).setdefault(world, {})[label] = row
    return out


def format_by_world(worlds: dict, labels: Sequence[str]) -> str:
    """Markdown of :func:`by_world`: per set, a row per world, a column per model: success [95% CI],
    with ``*`` where the paired difference from open-loop replay has two-sided p < 0.05 and ``v`` where
    the model is below open-loop replay with p < 0.05.

    Examples:
        >>> row = {"success": {"mean": 0.5, "ci": [0.4, 0.6]}, "vs_open_loop": {"success": {"difference": -0.2, "p_two_sided": 0.01}}}
        >>> print(format_by_world({"test": {"none": {"m": row}}}, ["m"]).splitlines()[4])
        | none | 0.50 [0.40, 0.60] v |
    """
    lines: list[str] = []
    for set_name, rows in worlds.items():
        lines += [f"**{set_name}**", "", "| world | " + " | ".join(labels) + " |", "|---" * (1 + len(labels)) + "|"]
        for world, models in rows.items():
            entries = []
            for label in labels:
                row = models.get(label)
                if row is None:
                    entries.append("-")
                    continue
                paired = row.get("vs_open_loop", {}).get("success")
                mark = ""
                if paired is not None and paired["p_two_sided"] < ALPHA:
                    mark = " v" if paired["difference"] < 0 else "*"
                low, high = row["success"]["ci"]
                entries.append(f"{row['success']['mean']:.2f} [{low:.2f}, {high:.2f}]{mark}")
            lines.append(f"| {world} | " + " | ".join(entries) + " |")
        lines.append("")
    lines.append("success, pooled over the world's cells (styles x lengths), 95% house-level bootstrap interval; * above "
                 "open-loop replay, v below it (paired on the same episodes, two-sided p < 0.05).")
    return "\n".join(lines)


def format_vs_reference(worlds: dict, labels: Sequence[str], reference: str) -> str:
    """Markdown of :func:`by_world`'s ``vs_reference``: per set, a row per world, a column per model (but the
    reference and open-loop replay): the paired difference in success from ``reference`` with its 95%
    interval, ``*`` where two-sided p < 0.05.

    Examples:
        >>> row = {"vs_reference": {"success": {"difference": 0.21, "ci": [0.12, 0.3], "p_two_sided": 0.001}}}
        >>> print(format_vs_reference({"test": {"light@1.0": {"m": row}}}, ["open_loop", "ref", "m"], "ref").splitlines()[4])
        | light@1.0 | +0.21 [+0.12, +0.30]* |
    """
    shown = [label for label in labels if label not in (OPEN_LOOP, reference)]
    lines: list[str] = []
    for set_name, rows in worlds.items():
        lines += [f"**{set_name}**: success minus {reference}'s", "", "| world | " + " | ".join(shown) + " |",
                  "|---" * (1 + len(shown)) + "|"]
        for world, models in rows.items():
            entries = []
            for label in shown:
                paired = (models.get(label) or {}).get("vs_reference", {}).get("success")
                if paired is None:
                    entries.append("-")
                    continue
                low, high = paired["ci"]
                mark = "*" if paired["p_two_sided"] < ALPHA else ""
                entries.append(f"{paired['difference']:+.2f} [{low:+.2f}, {high:+.2f}]{mark}")
            lines.append(f"| {world} | " + " | ".join(entries) + " |")
        lines.append("")
    lines.append("paired on the same episodes (house-level bootstrap), 95% interval; * two-sided p < 0.05.")
    return "\n".join(lines)


def plot_bench(content: dict, path: str | Path) -> Path:
    """Success (95% CI) by length bucket, a panel per set (row) and style (column), a line per model, to a PNG."""
    from spf_rl.viz import pyplot, save_figure

    plt = pyplot()
    setup = content["setup"]
    sets, styles, buckets = list(setup["sets"]), setup["styles"], [tuple(b) for b in setup["buckets"]]
    fig, axes = plt.subplots(len(sets), len(styles), figsize=(3.6 * len(styles), 3.0 * len(sets)), squeeze=False, sharey=True)
    for i, set_name in enumerate(sets):
        for j, style in enumerate(styles):
            ax = axes[i][j]
            labels = report_labels(setup)
            for k, label in enumerate(labels):
                xs, ys, errors = [], [], []
                for x, bucket in enumerate(buckets):
                    row = (content["cells"].get(cell_key(set_name, style, bucket), {}).get("stats") or {}).get(label)
                    if row is not None:
                        mean, (low, high) = row["success"]["mean"], row["success"]["ci"]
                        xs.append(x + 0.04 * (k - len(labels) / 2))
                        ys.append(mean)
                        errors.append((mean - low, high - mean))
                if xs:
                    style_kw = {"color": "black", "linestyle": "--"} if label == OPEN_LOOP else {"linestyle": "-"}
                    ax.errorbar(xs, ys, yerr=np.asarray(errors).T, fmt="o", capsize=2, markersize=3, label=label, **style_kw)
            ax.set_xticks(range(len(buckets)), [bucket_name(b) for b in buckets])
            ax.set_xlim(-0.5, len(buckets) - 0.5)
            ax.set_ylim(0, 1.02)
            ax.set_title(f"{style} ({set_name})", fontsize=9)
            ax.set_xlabel("route length (steps)")
            if j == 0:
                ax.set_ylabel("success (95% CI)")
    axes[0][0].legend(fontsize=6)
    return save_figure(fig, path, f"route benchmark: success by route length ({setup['episodes']} episodes per cell, "
                                  f"{setup['noise']} noise)")


def plot_worlds(content: dict, path: str | Path) -> Path:
    """Success (95% CI) per world of the condition axis (:func:`by_world`), a bar per model, a panel per set, to a PNG."""
    from spf_rl.viz import pyplot, save_figure

    plt = pyplot()
    worlds = content["by_world"]
    labels = report_labels(content["setup"])
    fig, axes = plt.subplots(len(worlds), 1, figsize=(max(6.0, 1.2 * len(next(iter(worlds.values())))), 3.6 * len(worlds)), squeeze=False)
    width = 0.8 / len(labels)
    for ax, (set_name, rows) in zip(axes[:, 0], worlds.items()):
        names = list(rows)
        for k, label in enumerate(labels):
            xs = [i + (k - (len(labels) - 1) / 2) * width for i, world in enumerate(names) if label in rows[world]]
            means = [rows[world][label]["success"]["mean"] for world in names if label in rows[world]]
            errors = [(rows[w][label]["success"]["mean"] - rows[w][label]["success"]["ci"][0],
                       rows[w][label]["success"]["ci"][1] - rows[w][label]["success"]["mean"]) for w in names if label in rows[w]]
            style = {"color": "lightgray", "edgecolor": "black", "hatch": "//"} if label == OPEN_LOOP else {}
            ax.bar(xs, means, width, yerr=np.asarray(errors).T if errors else None, capsize=2, label=label, **style)
        ax.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=8)
        ax.set_ylim(0, 1.02)
        ax.set_ylabel("success (95% CI)")
        ax.set_title(set_name, fontsize=9)
    axes[0][0].legend(fontsize=6, ncol=2)
    setup = content["setup"]
    return save_figure(fig, path, f"route benchmark by world: success pooled over styles and lengths ({setup['episodes']} episodes per cell)")


# ------------------------------------------------------------------------ the run
def setup_of(options: BenchOptions, models: list[BenchModel]) -> dict:
    """The set-up written to the JSON."""
    from envs.version import ENV_VERSION

    return {
        "episodes": options.episodes, "seed": options.seed, "noise": options.noise, "split": "test",
        "sets": dict(options.set_houses), "styles": list(options.styles), "buckets": [list(b) for b in options.buckets],
        "max_steps": "each route's own: ceil(5/3 n)", "image_size": options.image_size, "num_resamples": options.num_resamples,
        "random_sparsity": options.random_sparsity, "env_version": ENV_VERSION, "conditions": list(options.conditions),
        "models": {m.label: dict(m.info) for m in models},
        "seed_groups": seed_groups([m.label for m in models]),
        "reference": options.reference,
    }


def load_previous(path: Path) -> dict:
    """The cells of an earlier run's JSON at ``path`` (``{}`` if there is none, or it is unreadable)."""
    import json

    if not path.is_file():
        return {}
    try:
        return dict(json.loads(path.read_text())["cells"])
    except (ValueError, KeyError, TypeError) as err:
        logger.warning("%s is unreadable (%s): starting afresh", path, err)
        return {}


def episodes_of(records: list[dict]) -> dict:
    return {key: [r[key] for r in records] for key in EPISODE_KEYS}


def run_bench(options: BenchOptions, models: list[BenchModel] | None = None) -> dict:
    """Evaluate every model and open-loop replay on every cell of ``options`` (skipping what ``options.out``
    already holds for the same episodes and checkpoints), then write the JSON, ``.md`` table and ``.png`` figure.
    ``models``: :func:`load_models` of ``options``, if the caller has loaded them already (to check them first).

    The JSON is written after every evaluation (a cell's statistics once all its models have played), so an
    interrupted run keeps its results and a rerun resumes; what an earlier file holds for other episodes,
    checkpoints or models is dropped (logged).

    Returns:
        The JSON content: ``recipe``, ``setup``, ``statistics``, ``cells`` (``{key: {set, style, bucket,
        key, episodes, models: {label: {policy_sha256, columns}}, stats}}``, records as per-episode columns in
        the order of ``episodes``), ``by_style`` (:func:`by_style`), ``table`` and ``table_by_model`` (markdown) and ``figure``.

    Raises:
        ValueError: two models of a cell played different episodes.
    """
    models = load_models(options) if models is None else models
    out = Path(options.out)
    previous = load_previous(out)
    content = {"recipe": RECIPE, "setup": setup_of(options, models), "statistics": STATISTICS, "cells": {}}
    plan = [(w, s, style, b) for w in options.conditions for s in options.sets for style in options.styles for b in options.buckets]
    for world, set_name, style, bucket in plan:
        key = cell_key(set_name, style, bucket, world)
        config = cell_config(options, set_name, style, bucket, world)
        identity = episodes_key(config)
        old = previous.pop(key, None)
        if old is not None and (changed := changed_fields(old.get("key"), identity)):
            logger.info("%s: the file's episodes were made with other %s: evaluating again", key, ", ".join(changed))
            old = None
        cell = {"set": set_name, "style": style, "bucket": list(bucket), "world": world, "key": identity,
                "episodes": (old or {}).get("episodes"), "models": {}, "stats": None}
        content["cells"][key] = cell
        for model in models:
            done = (old or {}).get("models", {}).get(model.label)
            weights = model.policy_sha256(config.episodes.demo_length)
            if done is not None and done.get("policy_sha256") == weights:
                cell["models"][model.label] = done
                continue
            logger.info("%s: %s on %d episodes", key, model.label, options.episodes)
            records = evaluate_model(model, config, options.progress)
            episodes = episodes_of(records)
            if cell["episodes"] is None:
                cell["episodes"] = episodes
            elif episodes != cell["episodes"]:
                raise ValueError(f"{key}: {model.label} played other episodes than the cell's first model")
            cell["models"][model.label] = {"policy_sha256": weights, "columns": to_columns(records, BENCH_RECORD_FIELDS)}
            atomic_write_json(out, content, indent=1)
        cell["stats"] = cell_stats(cell, options.num_resamples)
        logger.info("%s: success %s", key, ", ".join(f"{label} {row['success']['mean']:.2f}" for label, row in cell["stats"].items()))
        atomic_write_json(out, content, indent=1)
        for label in set((old or {}).get("models", {})) - set(cell["models"]):
            logger.warning("%s: dropping the file's records of %s (not a model of this run)", key, label)
    for key in previous:
        logger.warning("dropping the file's cell %s (not a cell of this run)", key)
    content["table"] = format_table(content)
    content["table_by_model"] = format_by_model(content)
    content["by_style"] = by_style(content)
    worlds = options.conditions != (None,)
    if worlds or options.reference is not None:
        content["by_world"] = by_world(content, options.num_resamples)
    if worlds:
        content["table_by_world"] = format_by_world(content["by_world"], report_labels(content["setup"]))
    if options.reference is not None:
        content["table_vs_reference"] = format_vs_reference(content["by_world"], report_labels(content["setup"]),
                                                            options.reference)
    from spf_rl.viz import plot_if_available

    plot = plot_worlds if worlds else plot_bench
    figure = plot_if_available(plot, content, out.with_suffix(".png"))
    content["figure"] = None if figure is None else str(figure)
    atomic_write_json(out, content, indent=1)
    from envs.atomic_io import atomic_write_text

    tables = [content.get("table_by_world"), content.get("table_vs_reference"), content["table"], content["table_by_model"]]
    atomic_write_text(out.with_suffix(".md"), "\n\n".join(t for t in tables if t) + "\n")
    return content

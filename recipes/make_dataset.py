"""Generate (or resume) the expert-labelled follow-episode dataset that ``recipes/bc.py`` trains on.

Takes the same configuration as ``bc.py`` (``recipes/configs/bc.yaml`` and the main job's
``bc_main.yaml``, their ``data`` section and ``data_dir``), so ``bc.py`` reuses what this writes.
Interrupt it at any time and run it again to resume.

Usage::

    python recipes/make_dataset.py                      # the default 2000 episodes
    python recipes/make_dataset.py data.num_episodes=500 data.noise=locobot num_workers=2
"""
from __future__ import annotations

import argparse
import json
import logging

from spf_rl.cli import ArgumentParser
from spf_rl.config import config_or_exit, load_config


def main(argv: list[str] | None = None) -> dict:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="the --quick preset's small dataset")
    parser.add_argument("overrides", nargs="*", help="key=value config overrides (as for bc.py)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    import envs  # noqa: F401
    from spf_rl.data import EpisodeDataset
    from spf_rl.train.bc import MAIN_JOB_PRESET, BCConfig

    preset = "bc_quick" if args.quick else MAIN_JOB_PRESET
    config = config_or_exit(parser, load_config, BCConfig, "bc", args.overrides, preset=preset)
    root = config.resolved_data_dir()
    dataset = EpisodeDataset.build(root, config.data, num_workers=config.num_workers, progress=config.progress)
    dataset.verify()
    stats = {"path": str(root), **dataset.statistics()}
    print(json.dumps(stats, indent=2))
    return stats


if __name__ == "__main__":
    main()

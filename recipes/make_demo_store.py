"""Build (or reopen) a store of pre-rendered demonstrations for fast collection.

A :class:`~envs.demo_store.DemoStore` holds ``num_demos`` demonstrations of a
split, sampled and rendered once; envs given ``demo_store=<root>`` draw their
episodes from it and can emit ``demo_id`` instead of the frames
(``emit_demo_frames=False``), which is the fast collection path measured by
``benchmarks/bench_env.py``. The store is a pure function of its configuration;
an existing store with the same configuration is reopened and verified, not
rebuilt.

Usage::

    python recipes/make_demo_store.py                               # 1000 train demonstrations
    python recipes/make_demo_store.py store.split=val store.num_demos=200 root=data/demo_stores/val
"""
from __future__ import annotations

import argparse
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from envs.demo_store import DemoStoreConfig
from spf_rl.cli import ArgumentParser
from spf_rl.config import config_or_exit, load_config

REPO_ROOT = Path(__file__).resolve().parents[1]


@dataclass
class MakeDemoStoreConfig:
    """Where the store goes and what it holds.

    Args:
        root: the store directory; empty for a name derived from ``store``, under ``data/demo_stores``.
        progress: show a progress bar.
        store: the :class:`~envs.demo_store.DemoStoreConfig`.
    """

    root: str = ""
    progress: bool = True
    store: DemoStoreConfig = field(default_factory=DemoStoreConfig)

    def resolved_root(self) -> Path:
        if self.root:
            return Path(self.root)
        c, e = self.store, self.store.episodes
        houses = "default" if e.num_houses is None else e.num_houses
        name = f"{e.split}-k{c.num_demos}-h{houses}-n{e.demo_length}-s{e.image_size}-seed{e.seed}"
        return REPO_ROOT / "data" / "demo_stores" / name


def main(argv: list[str] | None = None) -> dict:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("overrides", nargs="*", help="key=value config overrides, e.g. store.num_demos=200")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    import envs  # noqa: F401  (selects the GL back-end)
    from envs.demo_store import DemoStore

    config = config_or_exit(parser, load_config, MakeDemoStoreConfig, "demo_store", args.overrides)
    root = config.resolved_root()
    store = DemoStore.build(root, config.store, progress=config.progress)
    store.verify()
    summary = {
        "root": str(root),
        "num_demos": len(store),
        "houses": len(set(store.house_seeds.tolist())),
        "mean_route_length_m": round(float(store.shortest_lengths_m.mean()), 3),
        "frames_shape": list(store.frames.shape),
    }
    print(json.dumps(summary, indent=2))
    return summary


if __name__ == "__main__":
    main()

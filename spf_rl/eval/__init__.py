"""Studies and reports over evaluation records, the library side of their recipes:

* :mod:`spf_rl.eval.table1`: Table 1's statistics, per-episode cache, claims and reports;
* :mod:`spf_rl.eval.table1_rows`: its rows, the runs behind them, shipping, scoring and the
  whole run (``recipes/table1.py`` is the command line of both);
* :mod:`spf_rl.eval.checkpoints`: checkpoints (or open-loop replay) evaluated on a split, one
  JSON each (``recipes/evaluate.py``);
* :mod:`spf_rl.eval.by_length`: success against route length (``recipes/success_by_length.py``);
* :mod:`spf_rl.eval.paired`: paired comparisons of two evaluations of the same episodes
  (``recipes/paired.py``);
* :mod:`spf_rl.eval.picking`: how well validation picks checkpoints (``recipes/picking_study.py``);
* :mod:`spf_rl.eval.scripted`: the expert's and open-loop replay's scores (``recipes/expert_stats.py``).
* :mod:`spf_rl.eval.route_bench`: every shipped policy and open-loop replay over route style x
  length (``recipes/route_bench.py``).
"""

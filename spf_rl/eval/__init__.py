"""Studies and reports over evaluation records, the library side of their recipes:

* :mod:`spf_rl.eval.table1`: Table 1's statistics, per-episode cache, claims and reports;
* :mod:`spf_rl.eval.table1_rows`: its rows, the runs behind them, shipping and scoring
  (``recipes/table1.py`` is the command line of both);
* :mod:`spf_rl.eval.paired`: paired comparisons of two evaluations of the same episodes
  (``recipes/paired.py``);
* :mod:`spf_rl.eval.picking`: how well validation picks checkpoints (``recipes/picking_study.py``);
* :mod:`spf_rl.eval.scripted`: the expert's and open-loop replay's scores (``recipes/expert_stats.py``).
"""

"""Studies and reports over evaluation records, the library side of their recipes:

* :mod:`spf_rl.eval.table1`: Table 1's statistics, per-episode cache, claims and reports
  (``recipes/table1.py``);
* :mod:`spf_rl.eval.paired`: paired comparisons of two evaluations of the same episodes
  (``recipes/paired.py``);
* :mod:`spf_rl.eval.picking`: how well validation picks checkpoints
  (``recipes/picking_study.py``).
"""

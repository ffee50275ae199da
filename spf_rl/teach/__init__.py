"""Teaching a route: take it as actions, waypoints or from the keyboard (:mod:`spf_rl.teach.route`,
the keyboard in :mod:`spf_rl.teach.keyboard`), let a policy repeat it and draw what happened
(:mod:`spf_rl.teach.repeat`). ``recipes/teach.py`` is the command line."""

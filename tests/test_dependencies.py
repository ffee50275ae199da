"""The library imports only its core dependencies: figures and GIFs (the viz extra) load on use."""
from __future__ import annotations

import subprocess
import sys

# every module of envs/ and spf_rl/, then which of the viz extra's packages got imported
SCRIPT = """
import importlib, pkgutil, sys
import envs, spf_rl
for package in (envs, spf_rl):
    for module in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
        importlib.import_module(module.name)
print(sorted(name for name in ("matplotlib", "imageio") if name in sys.modules))
"""


def test_library_imports_without_the_viz_extra():
    result = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300, check=True)
    assert result.stdout.strip().splitlines()[-1] == "[]"


def test_without_matplotlib_a_figure_is_skipped_with_a_hint(monkeypatch, tmp_path, caplog):
    from spf_rl.viz import plot_if_available, plot_training_curves

    monkeypatch.setitem(sys.modules, "matplotlib.pyplot", None)  # import fails as if not installed
    history = [{"epoch": 1, "train_loss": 1.0, "train_accuracy": 0.5, "val_success": 0.2, "val_spl": 0.1}]
    assert plot_if_available(plot_training_curves, history, tmp_path / "c.png") is None
    assert not (tmp_path / "c.png").exists()
    assert 'pip install -e ".[viz]"' in caplog.text

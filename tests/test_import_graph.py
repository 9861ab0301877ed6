"""The engine's import graph (python -m tools import-graph): no cycles, every arrow down."""
from __future__ import annotations

from tools import import_graph
from tools.__main__ import main


def test_engine_graph_has_no_cycles_upward_arrows_or_bpy(capsys):
    assert import_graph.check() == []
    assert main(["import-graph"]) == 0
    assert "OK (no cycles" in capsys.readouterr().out


def test_the_check_catches_cycles_upward_arrows_bpy_and_size(tmp_path):
    root = tmp_path / "engine"
    for pkg in ("", "io", "scene", "train"):
        (root / pkg).mkdir(parents=True, exist_ok=True)
        (root / pkg / "__init__.py").write_text("")
    (root / "io" / "capture.py").write_text("from ..scene.model import Model4D\n")          # io -> scene: up
    (root / "scene" / "model.py").write_text("from ..train import trainer\nimport bpy\n")     # scene -> train: up
    (root / "train" / "trainer.py").write_text("from . import losses\n")
    (root / "train" / "losses.py").write_text("def f():\n    from .trainer import x\n")      # a lazy circle
    (root / "train" / "big.py").write_text("x = 1\n" * 30)
    problems = "\n".join(import_graph.check(root, max_lines=20))
    assert "engine.io.capture (io) imports engine.scene.model (scene): an arrow pointing up" in problems
    assert "engine.scene.model (scene) imports engine.train.trainer (train)" in problems
    assert "imports bpy" in problems
    assert "import cycle: engine.train.losses -> engine.train.trainer" in problems
    assert "big.py:1: 30 lines" in problems


def test_the_check_keeps_the_order_of_the_parts_of_training(tmp_path):
    """Inside engine.train: config < frames < losses < motion < guidance < skipping < loop."""
    root = tmp_path / "engine"
    for pkg in ("", "train", "train/losses", "train/guidance", "train/loop"):
        (root / pkg).mkdir(parents=True, exist_ok=True)
        (root / pkg / "__init__.py").write_text("")
    (root / "train" / "config.py").write_text("")
    (root / "train" / "losses" / "terms.py").write_text("from ..guidance import spike_guidance\n")  # up
    (root / "train" / "guidance" / "spike_guidance.py").write_text("from ..config import x\n")  # down
    (root / "train" / "loop" / "trainer.py").write_text("from ..config import y\nfrom ..guidance import z\n")
    problems = import_graph.check(root)
    assert problems == ["engine/train/losses/terms.py:1: engine.train.losses.terms (train.losses) imports "
                        "engine.train.guidance.spike_guidance (train.guidance): an arrow pointing up"], problems


def test_engine_top_level_names_and_subpackages(repo_root):
    """``engine.train`` is the package whatever was imported first; the lazy names resolve."""
    import subprocess
    import sys

    code = ("import types, engine\n"
            "from engine import load_run, rasterization, tfp\n"  # the lazy names first ...
            "assert isinstance(engine.train, types.ModuleType), engine.train\n"  # ... then the package
            "assert callable(engine.train.train) and engine.train.TrainConfig and engine.train.get_preset\n"
            "assert callable(engine.evaluate.evaluate)\n"
            "for n in ('load_capture', 'Capture', 'read_spikes', 'write_spikes', 'SpikeStream', 'simulate_spikes',\n"
            "          'tfp', 'tfi', 'rasterization', 'load_run'):\n"
            "    assert getattr(engine, n) is not None, n\n"
            "print('ok')\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=repo_root, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr

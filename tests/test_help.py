"""`--help` of the training commands shows each default once, and none for required flags."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize(
    "module, required, defaulted",
    [
        ("training.train", "--policy {mse,flow} policy kind: mse or flow --name", "(default: 200000)"),
        ("training.recipe", "recipe the recipe file, e.g. recipes/flow.toml", "(default: runs/recipes)"),
        ("training.collect", "--model MODEL an ONNX file or a checkpoint stem --out OUT", "(default: 10000000)"),
        ("training.finetune", "--init INIT flow checkpoint stem to fine-tune", "(default: 0.2)"),
        (
            "training.ship",
            "--run RUN the finished run folder written by training.train (has last.* and best.*) --name",
            "(default: records)",
        ),
        (
            "training.evaluate",
            "--model MODEL an ONNX file (models/flow.onnx, card NAME.json beside it) or a checkpoint stem (models/flow) --episodes",
            "(default: 200000)",
        ),
    ],
)
def test_help_shows_defaults_once(module, required, defaulted):
    done = subprocess.run([sys.executable, "-m", module, "--help"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    text = " ".join(done.stdout.split())  # argparse wraps lines
    assert "(default: None)" not in text and "(default: )" not in text
    assert not re.search(r"\(default: [^)]*\) \(default:", text), text
    assert required in text and defaulted in text

"""Startup refuses bad configuration with one line naming the problem, no traceback, no hang.

Each case starts a real server (plain `uvicorn service.app:app`, and for some `python -m service`)
on loopback and expects it to exit non-zero, naming the PUSHT_ variable or the file.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from tests.service_fixtures import REPO, free_port, server_command


def _copy_models(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for f in src.iterdir():
        if f.is_file():
            (dst / f.name).write_bytes(f.read_bytes())
    return dst


def _nan_flow(models: Path) -> None:
    """Give models/flow.onnx NaN weights (training refuses to save such weights, so edit the exported graph)."""
    import numpy as np
    import onnx
    from onnx import numpy_helper

    model = onnx.load(models / "flow.onnx")
    for i, init in enumerate(model.graph.initializer):
        array = numpy_helper.to_array(init)
        if array.dtype == np.float32 and array.ndim == 2:
            model.graph.initializer[i].CopyFrom(numpy_helper.from_array(np.full_like(array, np.nan), init.name))
            break
    onnx.save(model, models / "flow.onnx")


def _start(entry: str, env: dict[str, str], timeout: float = 90) -> subprocess.CompletedProcess:
    """Start the server as users do and wait for it to exit (it must: every case here is refused)."""
    return subprocess.run(
        server_command(entry, free_port()),
        cwd=REPO,
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _assert_refused(proc: subprocess.CompletedProcess, *needles: str) -> None:
    output = proc.stdout + proc.stderr
    assert proc.returncode != 0, output[-2000:]
    assert "Traceback" not in output, output[-3000:]
    lines = [line for line in output.splitlines() if "cannot start" in line]
    assert len(lines) == 1, output[-3000:]
    for needle in needles:
        assert needle in lines[0], lines[0]


SETTINGS_CASES = [
    ("empty key", {"PUSHT_API_KEY": ""}, "PUSHT_API_KEY"),
    ("whitespace key", {"PUSHT_API_KEY": "   "}, "PUSHT_API_KEY"),
    ("key with spaces around", {"PUSHT_API_KEY": " s3cret "}, "PUSHT_API_KEY"),
    ("not a number", {"PUSHT_MAX_STATES": "lots"}, "PUSHT_MAX_STATES"),
    ("out of range", {"PUSHT_BATCH_MAX_COST": "0"}, "PUSHT_BATCH_MAX_COST"),
    ("unknown backend", {"PUSHT_BACKEND": "tensorflow"}, "PUSHT_BACKEND"),
]


@pytest.mark.slow
@pytest.mark.parametrize("entry", ["uvicorn", "service"])
@pytest.mark.parametrize("case, env, variable", SETTINGS_CASES, ids=[c[0] for c in SETTINGS_CASES])
def test_bad_setting_names_its_variable(entry: str, case: str, env: dict, variable: str, test_models: Path) -> None:
    proc = _start(entry, {"PUSHT_MODELS_DIR": str(test_models), **env})
    _assert_refused(proc, variable)
    if "KEY" in variable:
        assert "s3cret" not in proc.stdout + proc.stderr  # the key is never echoed


def _break(kind: str, models: Path) -> Path:
    """Break one file of a copy of the test models; returns the path the refusal must name."""
    card = models / "flow.json"
    good = json.loads(card.read_text())
    if kind == "card {}":
        card.write_text("{}")
    elif kind == "card null":
        card.write_text("null")
    elif kind == "card a list":
        card.write_text("[1, 2]")
    elif kind == "onnx a string":
        card.write_text(json.dumps({**good, "onnx": "flow.onnx"}))
    elif kind == "nested 100k deep":
        card.write_text("[" * 100_000 + "]" * 100_000)
    elif kind == "card a FIFO":
        card.unlink()
        os.mkfifo(card)
    elif kind == "card a directory":
        card.unlink()
        card.mkdir()
    elif kind == "onnx a FIFO":
        (models / "flow.onnx").unlink()
        os.mkfifo(models / "flow.onnx")
        return models / "flow.onnx"
    elif kind == "stray JSON":
        card = models / "notes.json"
        card.write_text('{"comment": "not a card"}')
    elif kind == "NaN weights":
        _nan_flow(models)
        return models / "flow.onnx"
    else:
        raise ValueError(kind)
    return card


CARD_CASES = [
    "card {}",
    "card null",
    "card a list",
    "onnx a string",
    "nested 100k deep",
    "card a FIFO",
    "card a directory",
    "onnx a FIFO",
    "stray JSON",
    "NaN weights",
]


@pytest.mark.slow
@pytest.mark.parametrize("kind", CARD_CASES)
def test_one_bad_policy_stops_startup_naming_the_file(kind: str, test_models: Path, tmp_path: Path) -> None:
    """Plain uvicorn, as users start it: exits (a FIFO must not hang it) with one line naming the file."""
    models = _copy_models(test_models, tmp_path / "models")
    bad = _break(kind, models)
    proc = _start("uvicorn", {"PUSHT_MODELS_DIR": str(models)})
    _assert_refused(proc, str(bad))
    if kind == "NaN weights":
        assert "not finite" in proc.stderr


@pytest.mark.slow
def test_python_m_service_refuses_a_bad_card_in_one_line(test_models: Path, tmp_path: Path) -> None:
    models = _copy_models(test_models, tmp_path / "models")
    bad = _break("card null", models)
    _assert_refused(_start("service", {"PUSHT_MODELS_DIR": str(models)}), str(bad))

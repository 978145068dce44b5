"""The Docker image's install, without Docker: the Dockerfile's COPY and `pip install` steps in a fresh venv.

The steps are read from the Dockerfile itself, so the image and this test cannot drift apart. The
venv must not be able to import torch, and the service started from it (the Dockerfile's CMD, on
loopback) must answer /act and pass the Dockerfile's HEALTHCHECK.
"""

from __future__ import annotations

import fnmatch
import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from tests.service_fixtures import (
    REPO,
    SHIPPED_MODELS,
    UvicornProcess,
    cached_test_models,
    shipped_models_available,
)

DOCKERFILE = REPO / "Dockerfile"


def dockerfile_instructions(path: Path = DOCKERFILE) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs, continuation lines joined, comments dropped."""
    joined: list[str] = []
    pending = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        joined.append(pending + line)
        pending = ""
    return [(line.split(None, 1)[0].upper(), line.split(None, 1)[1]) for line in joined]


def dockerignore_patterns(path: Path = REPO / ".dockerignore") -> list[str]:
    """The .dockerignore patterns (comments and blank lines dropped)."""
    lines = (line.strip() for line in path.read_text().splitlines())
    return [line.rstrip("/") for line in lines if line and not line.startswith("#")]


def is_ignored(rel: Path, patterns: list[str]) -> bool:
    """Whether the build-context path `rel` (or a folder above it) matches a .dockerignore pattern."""
    candidates = [rel, *rel.parents][:-1]  # the path and its parent folders, without "."
    return any(fnmatch.fnmatch(str(c), p) or fnmatch.fnmatch(str(c), p.replace("**/", "")) for c in candidates for p in patterns)


def _copy(src: Path, target: Path, rel: Path, ignored: list[str]) -> None:
    """Copy as `COPY` from a context filtered by .dockerignore would (plus our fixture's marker file)."""
    if is_ignored(rel, ignored) or src.name == ".complete":
        return
    if src.is_dir():
        target.mkdir(parents=True, exist_ok=True)
        for child in src.iterdir():
            _copy(child, target / child.name, rel / child.name, ignored)
    else:
        shutil.copy2(src, target)


def test_dockerignore_keeps_checkpoints_and_caches_out() -> None:
    patterns = dockerignore_patterns()
    assert is_ignored(Path("models/flow.safetensors"), patterns)
    assert is_ignored(Path("models/runs/flow-x/best.json"), patterns)
    assert is_ignored(Path("service/__pycache__/app.cpython-311.pyc"), patterns)
    assert is_ignored(Path(".venv/bin/python"), patterns)
    assert not is_ignored(Path("models/flow.onnx"), patterns)
    assert not is_ignored(Path("models/flow.json"), patterns)
    assert not is_ignored(Path("service/app.py"), patterns)
    assert not is_ignored(Path("pusht/rollout.py"), patterns)
    assert not is_ignored(Path("acting/policy.py"), patterns)


def test_dockerfile_has_what_the_image_needs() -> None:
    """python:3.11-slim, the serve extra only, a non-root user, port 8000, a /readyz health check, `python -m service` CMD."""
    steps = dockerfile_instructions()
    by_kind: dict[str, list[str]] = {}
    for kind, args in steps:
        by_kind.setdefault(kind, []).append(args)
    assert by_kind["FROM"] == ["python:3.11-slim"]
    installs = [a for a in by_kind["RUN"] if a.startswith("pip install")]
    assert installs == ['pip install ".[serve]"'], installs
    assert by_kind["USER"] and by_kind["USER"][-1] not in ("root", "0")
    assert by_kind["EXPOSE"] == ["8000"]
    assert "/readyz" in by_kind["HEALTHCHECK"][0] and "curl" not in by_kind["HEALTHCHECK"][0]
    # python -m service: uvicorn with the connection limits (header deadline, caps, bounded shutdown)
    assert json.loads(by_kind["CMD"][0]) == ["python", "-m", "service", "--host", "0.0.0.0", "--port", "8000"]
    assert any(a.startswith("models") for a in by_kind["COPY"])
    # the service loads every policy through the acting package (card reader, ONNX Runtime backend)
    copied = {shlex.split(a)[0] for a in by_kind["COPY"]}
    assert {"pusht", "acting", "service"} <= copied, copied


@pytest.mark.slow
def test_image_install_serves_without_torch(tmp_path: Path, tmp_path_factory: pytest.TempPathFactory) -> None:
    steps = dockerfile_instructions()
    context = tmp_path / "app"  # plays WORKDIR /app
    context.mkdir()
    models_src = SHIPPED_MODELS if shipped_models_available() else cached_test_models(tmp_path_factory.getbasetemp())
    ignored = dockerignore_patterns()
    for kind, args in steps:
        if kind != "COPY":
            continue
        *sources, dest = shlex.split(args)
        for source in sources:
            src = models_src if source == "models" else REPO / source
            target = context / dest if dest not in ("./", ".") else context / Path(source).name
            _copy(src, target, Path(source.rstrip("/")), ignored)
    assert not list((context / "models").glob("*.safetensors"))

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    install = next(args for kind, args in steps if kind == "RUN" and args.startswith("pip install"))
    cmd = [str(venv / "bin" / "python"), "-m", *shlex.split(install)]
    # The image sets PIP_NO_CACHE_DIR; here the local pip cache and wheel mirror keep it quick.
    result = subprocess.run(cmd, cwd=context, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]

    no_torch = subprocess.run([str(venv / "bin" / "python"), "-c", "import torch"], capture_output=True, text=True, cwd=tmp_path)
    assert no_torch.returncode != 0 and "No module named 'torch'" in no_torch.stderr

    cmd_line = json.loads(next(args for kind, args in steps if kind == "CMD"))
    assert cmd_line[:3] == ["python", "-m", "service"]
    env = {"PUSHT_MODELS_DIR": str(context / "models"), "PUSHT_BACKEND": "onnx", "PYTHONPATH": ""}
    with UvicornProcess(env, python=str(venv / "bin" / "python"), cwd=context, entry="service") as srv:
        assert httpx.get(f"{srv.url}/docs-assets/swagger-ui-bundle.js").status_code == 200  # /docs works offline
        answer = httpx.post(f"{srv.url}/act", json={"policy": "flow", "state": [222.0, 97.0, 222.0, 222.0, 0.8], "seed": 0})
        assert answer.status_code == 200, answer.text
        assert answer.json()["backend"] == "onnx"
        health = next(args for kind, args in steps if kind == "HEALTHCHECK")
        probe = json.loads(health.split("CMD", 1)[1])  # the exec (JSON array) form
        assert probe[0] == "python"
        probe = [str(venv / "bin" / "python"), *probe[1:]]
        probe[-1] = probe[-1].replace("127.0.0.1:8000", f"127.0.0.1:{srv.port}")
        assert subprocess.run(probe, timeout=30).returncode == 0

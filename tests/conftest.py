"""Shared fixtures: the random-weight test models and a real server over them or the shipped ones (service tests); real windows (policy tests)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.service_fixtures import (
    SHIPPED_MODELS,
    UvicornProcess,
    cached_chooser_models,
    cached_test_models,
    shipped_models_available,
)


@pytest.fixture(scope="session")
def test_models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Random-weight mse and flow policies (cards, safetensors, ONNX)."""
    return cached_test_models(tmp_path_factory.getbasetemp())


@pytest.fixture(scope="session")
def horizon16_models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Random-weight mse and flow policies whose cards say 16-action chunks (not the default 12)."""
    return cached_test_models(tmp_path_factory.getbasetemp(), horizon=16)


@pytest.fixture(scope="session")
def chooser_models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shipped mse and the outcome chooser record as `flow` with its 10-step ONNX export (a flow with steps and noise)."""
    return cached_chooser_models(tmp_path_factory.getbasetemp())


@pytest.fixture(scope="module", params=["test", "shipped"], ids=["test-models", "shipped-models"])
def server(request: pytest.FixtureRequest):
    """A real uvicorn on 127.0.0.1 serving the random test models, then the shipped models/ (if present)."""
    if request.param == "shipped":
        if not shipped_models_available():
            pytest.skip("models/ has no shipped mse and flow")
        models_dir = SHIPPED_MODELS
    else:
        models_dir = request.getfixturevalue("test_models")
    with UvicornProcess({"PUSHT_MODELS_DIR": str(models_dir), "PUSHT_MAX_STATES": "64"}) as srv:
        yield srv


@pytest.fixture(scope="module")
def real_batch():
    """64 env-unit windows spread over the real dataset, and the training set (its `statistics` fit a policy)."""
    import torch

    from training.data import DEFAULT_DATASET, training_set

    data = training_set(DEFAULT_DATASET)
    idx = torch.linspace(0, len(data) - 1, 64).long()
    return data.states[idx], data.chunks[idx], data

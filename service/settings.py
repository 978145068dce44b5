"""Service settings, read once from the environment (prefix `PUSHT_`), e.g. `PUSHT_MODELS_DIR=models`."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

STATE_LIMIT = 1e4
"""Largest plausible |state value|: env states are pixels in 0..512 and an angle; far beyond is a client bug."""

MAX_NUM_STEPS = 100
"""Most flow Euler steps a request may ask for."""


class Settings(BaseSettings):
    """Everything that configures the service; each field is the env var `PUSHT_<FIELD>`."""

    model_config = SettingsConfigDict(env_prefix="PUSHT_", extra="ignore")

    models_dir: Path = Field(Path("models"), description="folder of policy cards NAME.json with NAME.onnx / NAME.safetensors")
    backend: Literal["onnx", "torch"] = Field("onnx", description="inference backend: ONNX Runtime, or torch (needs the train extra)")
    max_states: int = Field(1024, ge=1, description="most states in one request's `states` batch")
    batch_max_rows: int = Field(1024, ge=1, description="most state rows merged into one model call")
    batch_max_wait_ms: float = Field(
        0.0, ge=0.0, le=100.0,
        description=(
            "longest a request may wait for others to join its model call, applied only while calls merge several "
            "requests (under load); 0: merge just what queued while the previous call ran"
        ),
    )
    queue_limit: int = Field(
        65536, ge=1,
        description="most state rows waiting per policy before requests get 503 (never below 32 full requests: 32 * max_states)",
    )
    max_body_bytes: int = Field(1 << 20, ge=1024, description="largest accepted request body (bytes); larger gets 413")
    api_key: SecretStr | None = Field(None, description="when set, /act and /policies need `X-API-Key` or `Authorization: Bearer`")
    access_log: bool = Field(
        False, description="keep uvicorn's per-request access log lines (off: /metrics counts requests, and the log costs CPU per request)"
    )
    ort_intra_op_threads: int = Field(1, ge=0, description="ONNX Runtime intra-op threads per session (0: ORT default)")
    torch_threads: int = Field(1, ge=0, description="torch intra-op threads for the torch backend (0: torch default)")


@lru_cache
def get_settings() -> Settings:
    """The settings from the environment, read once per process."""
    return Settings()

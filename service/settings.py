"""Service settings, read once from the environment (prefix `PUSHT_`), e.g. `PUSHT_MODELS_DIR=models`."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, ValidationError, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from policies.card import MAX_NUM_STEPS

__all__ = ["MAX_NUM_STEPS", "STATE_LIMIT", "Settings", "SettingsError", "get_settings", "load_settings"]

STATE_LIMIT = 1e4
"""Largest plausible |state value|: env states are pixels in 0..512 and an angle; far beyond is a client bug."""
# MAX_NUM_STEPS (policies.card): the most flow Euler steps a request may ask for.


class SettingsError(ValueError):
    """A `PUSHT_*` variable has a bad value; the message names the variable."""


class Settings(BaseSettings):
    """Everything that configures the service; each field is the env var `PUSHT_<FIELD>`."""

    model_config = SettingsConfigDict(env_prefix="PUSHT_", extra="ignore")

    models_dir: Path = Field(Path("models"), description="folder of policy cards NAME.json with NAME.onnx / NAME.safetensors")
    default_policy: str = Field(
        "",
        max_length=200,
        description="policy that requests without a name get (default: the one whose card says `default`, else the first name)",
    )
    backend: Literal["onnx", "torch"] = Field(
        "onnx", description="inference backend: ONNX Runtime, or torch (needs the train extra)"
    )
    max_states: int = Field(1024, ge=1, description="most states in one request's `states` batch")
    batch_max_rows: int = Field(1024, ge=1, description="most state rows merged into one model call")
    batch_max_cost: int = Field(
        640,
        ge=1,
        description=(
            "most cost units (rows x network evaluations: num_steps per flow row, 1 per mse row) in one model call, "
            "though a call may always take one padded group of 4 rows; "
            "bulk batches are split across calls so that small requests never wait behind a long one"
        ),
    )
    inline_max_cost: int = Field(
        64,
        ge=0,
        description=(
            "a lone request of at most this many cost units, with nothing else queued, runs on the event loop instead of "
            "the policy's worker thread (the hop costs more than a small model call); 0: always the worker thread"
        ),
    )
    batch_max_wait_ms: float = Field(
        0.0,
        ge=0.0,
        le=100.0,
        description=(
            "longest a request may wait for others to join its model call, applied only while calls merge several "
            "requests (under load); 0: merge just what queued while the previous call ran"
        ),
    )
    queue_limit: int = Field(
        65536,
        ge=1,
        description=(
            "most queued cost units (rows x network evaluations) per policy before requests get 503 "
            "(never below 32 full requests at the default num_steps)"
        ),
    )
    max_body_bytes: int = Field(1 << 20, ge=1024, description="largest accepted request body (bytes); larger gets 413")
    max_header_bytes: int = Field(32768, ge=1024, description="largest accepted request line + headers (bytes); larger gets 431")
    body_timeout_s: float = Field(
        10.0, gt=0, le=600, description="longest a client may take to send a request body; slower gets 408"
    )
    header_timeout_s: float = Field(
        10.0,
        gt=0,
        le=600,
        description="`python -m service`: longest a connection may take to send a request's headers, then it is closed",
    )
    keep_alive_s: float = Field(
        5.0, gt=0, le=600, description="`python -m service`: idle keep-alive connections close after this long"
    )
    max_connections: int = Field(
        1000,
        ge=1,
        description="`python -m service`: most open connections (lowered to fit the file-descriptor limit); more get 503",
    )
    shutdown_timeout_s: float = Field(
        10.0, gt=0, le=600, description="`python -m service`: on SIGTERM, unfinished requests get this long"
    )
    api_key: SecretStr | None = Field(
        None, description="when set, /act and /policies need `X-API-Key` or `Authorization: Bearer`"
    )
    access_log: bool = Field(
        False,
        description="keep uvicorn's per-request access log lines (off: /metrics counts requests, and the log costs CPU per request)",
    )
    ort_intra_op_threads: int = Field(1, ge=0, description="ONNX Runtime intra-op threads per session (0: ORT default)")
    torch_threads: int = Field(1, ge=0, description="torch intra-op threads for the torch backend (0: torch default)")
    viewer_max_sessions: int = Field(
        4, ge=0, le=64, description="most live /viewer websocket sessions at once (0: viewer off); more get 503"
    )
    viewer_idle_s: float = Field(
        300.0,
        gt=0,
        le=3600,
        description="a /viewer session with no message from its page and no episode playing closes after this long",
    )
    viewer_data_dir: Path | None = Field(
        None, description="folder where /viewer saves episodes as zarr stores (unset: saving is off)"
    )

    @field_validator("api_key")
    @classmethod
    def _usable_key(cls, key: SecretStr | None) -> SecretStr | None:
        # An empty key would silently turn authentication off; HTTP strips header whitespace, so
        # surrounding whitespace would lock every client out.
        if key is not None:
            value = key.get_secret_value()
            if not value.strip():
                raise ValueError("is empty or whitespace only: unset it to serve without a key, or set a real key")
            if value != value.strip() or any(not 0x21 <= ord(c) <= 0x7E for c in value):
                raise ValueError("must be printable ASCII without spaces (clients send it in an HTTP header)")
        return key


def load_settings() -> Settings:
    """The settings from the environment; raise SettingsError naming the bad `PUSHT_` variable."""
    try:
        return Settings()
    except ValidationError as exc:
        problems = []
        for error in exc.errors(include_url=False):
            field = str(error["loc"][0]) if error.get("loc") else "?"
            shown = "" if field == "api_key" or "input" not in error else f"={error['input']!r}"
            problems.append(f"PUSHT_{field.upper()}{shown}: {error['msg']}")
        raise SettingsError("bad setting " + "; ".join(problems)) from None


@lru_cache
def get_settings() -> Settings:
    """The settings from the environment, read once per process."""
    return load_settings()

"""The shipped policies still do what they did when frozen (scripts/freeze_policies.py), on both backends."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))

import freeze_policies  # noqa: E402

SHIPPED = sorted(p.stem for p in (REPO / "models").glob("*.json"))


def test_every_shipped_policy_has_frozen_actions() -> None:
    assert SHIPPED and sorted(p.stem for p in freeze_policies.ARTIFACTS.glob("*.npz")) == SHIPPED


@pytest.mark.parametrize("backend", ["onnx", "torch"])
@pytest.mark.parametrize("name", SHIPPED)
def test_a_shipped_policy_acts_as_frozen(name: str, backend: str) -> None:
    stem = REPO / "models" / name
    frozen = np.load(freeze_policies.ARTIFACTS / f"{name}.npz")
    for suffix, key in ((".onnx", "onnx_sha256"), (".safetensors", "weights_sha256")):
        assert freeze_policies.sha256(stem.with_suffix(suffix)) == str(frozen[key]), (
            f"{stem}{suffix} changed since it was frozen: run python scripts/freeze_policies.py after shipping"
        )
    np.testing.assert_array_equal(frozen["states"], freeze_policies.probe_states())
    got = freeze_policies.actions(stem, backend, frozen["states"])
    # float32 kernels may round differently on another CPU; a changed policy moves actions by pixels, not by 1e-3
    np.testing.assert_allclose(got, frozen[backend], rtol=0, atol=1e-3, err_msg=f"{name} on {backend}")

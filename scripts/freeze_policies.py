"""Freeze the shipped policies' actions for fixed states and seeds into tests/artifacts/policies/NAME.npz.

    python scripts/freeze_policies.py            # after a recipe ships a new policy, and only then

tests/test_frozen_policies.py replays them on both backends: a refactor that changes what a shipped policy does fails it.
Each file also keeps the sha256 of the ONNX and weights files it was made from, so a re-shipped policy asks for a refreeze.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from acting import load_policy  # noqa: E402
from training.data import load_replay  # noqa: E402

ARTIFACTS = REPO / "tests" / "artifacts" / "policies"
FRAMES = (0, 40, 161, 500, 1200, 2400, 5000, 9000)  # demonstration states: the start, pushes, near-goal poses
SEEDS = tuple(range(100, 108))


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models-dir", default=str(REPO / "models"), help="the shipped policies")
    parser.add_argument("--out", default=str(ARTIFACTS), help="where the .npz files go")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for card in sorted(Path(args.models_dir).glob("*.json")):
        freeze(card.with_suffix(""), out / f"{card.stem}.npz")
        print(f"froze {card.stem} -> {out / card.stem}.npz")
    return 0


def probe_states(data: Path = REPO / "data" / "pusht_lowdim.zarr") -> np.ndarray:
    """The fixed states the artifacts are made of: a few demonstration frames."""
    return load_replay(data).states[list(FRAMES)].astype(np.float32)


def actions(stem: Path, backend: str, states: np.ndarray) -> np.ndarray:
    policy = load_policy(stem.with_suffix(".onnx") if backend == "onnx" else stem, backend=backend)
    return policy.act(states, seeds=list(SEEDS))


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def freeze(stem: Path, path: Path) -> None:
    states = probe_states()
    np.savez(
        path,
        states=states,
        seeds=np.asarray(SEEDS),
        onnx=actions(stem, "onnx", states),
        torch=actions(stem, "torch", states),
        onnx_sha256=sha256(stem.with_suffix(".onnx")),
        weights_sha256=sha256(stem.with_suffix(".safetensors")),
    )


if __name__ == "__main__":
    sys.exit(main())

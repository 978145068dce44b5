"""Convert checkpoints written before the policy owned its normalization (one-off; already done for models/ and records/).

    python scripts/convert_checkpoints.py runs/NAME/best runs/NAME/last ...

Sin/cos-angle policies used to save `angle_mean` and `angle_std`, copies of the angle's statistics in
the card's `normalization`. The policy's normalizer now takes every statistic from the card, so those
two weights go: each is checked to equal the card's value exactly (else nothing is written), the other
weights are written back unchanged, and the file is replaced atomically. A converted or plain
checkpoint is left as it is.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from policies.checkpoint import (  # noqa: E402
    CheckpointError,
    checkpoint_stem,
    load_card,
    load_checkpoint,
    read_tensors,
    write_tensors,
)
from policies.normalization import Normalizer  # noqa: E402

LEGACY_KEYS = ("angle_mean", "angle_std")


def convert(stem: str | Path) -> bool:
    """Drop the legacy angle buffers of checkpoint `stem` after checking them against its card; returns whether it changed."""
    stem = checkpoint_stem(stem)
    path = stem.with_suffix(".safetensors")
    card = load_card(stem)
    weights, metadata = read_tensors(path)
    if not set(LEGACY_KEYS) & set(weights):
        return False
    arch = card["architecture"]
    stats = Normalizer(arch.get("state_dim", 5), arch.get("action_dim", 2)).set(card["normalization"])
    for key, want in (("angle_mean", stats.state_mean[-1:]), ("angle_std", stats.state_std[-1:])):
        if not torch.equal(weights.get(key, torch.empty(0)), want):
            raise CheckpointError(
                f"{path}: {key} {weights.get(key)} differs from the card's normalization ({want}): not converted"
            )
    kept = {key: value for key, value in weights.items() if key not in LEGACY_KEYS}
    write_tensors(path, kept, metadata)
    load_checkpoint(stem)  # loads now
    return True


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stems", nargs="+", help="checkpoint stems (DIR/NAME for DIR/NAME.safetensors + DIR/NAME.json)")
    args = parser.parse_args(argv)
    try:
        for stem in args.stems:
            print(f"{stem}: {'converted' if convert(stem) else 'already current'}")
    except CheckpointError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Copy the low-dimensional arrays of the Push-T replay (no images) into a small zarr v2 store.

    python scripts/make_lowdim_dataset.py            # ../shared/data/pusht/... -> data/pusht_lowdim.zarr

Copies data/state, data/action, data/keypoint, data/n_contacts and meta/episode_ends with their
values unchanged, one blosc/zstd chunk per array, and checks the copy against the source.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np
import zarr
from numcodecs import Blosc
from tqdm import tqdm

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_SRC = REPO_ROOT.parent / "shared" / "data" / "pusht" / "pusht_cchi_v7_replay.zarr"
DEFAULT_OUT = REPO_ROOT / "data" / "pusht_lowdim.zarr"
ARRAYS = ("data/state", "data/action", "data/keypoint", "data/n_contacts", "meta/episode_ends")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(
        description="Copy the low-dimensional Push-T arrays (no images) into a small zarr v2 store, one zstd chunk per array.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--src", type=Path, default=DEFAULT_SRC, help="source replay zarr (pusht_cchi_v7_replay.zarr)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output zarr directory (replaced if it exists)")
    parser.add_argument("--clevel", type=int, default=9, help="zstd compression level")
    args = parser.parse_args(argv)
    try:
        copy_lowdim(args.src, args.out, clevel=args.clevel)
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    size = sum(f.stat().st_size for f in args.out.rglob("*") if f.is_file())
    print(f"wrote {args.out} ({size / 1e6:.2f} MB, {sum(1 for f in args.out.rglob('*') if f.is_file())} files)")
    return 0


def copy_lowdim(src: Path, out: Path, clevel: int = 9) -> None:
    """Copy ARRAYS from `src` to a fresh zarr v2 store at `out` and verify the values are identical."""
    if not src.is_dir():
        raise ValueError(f"{src}: source zarr not found")
    source = zarr.open_group(str(src), mode="r")
    for name in ARRAYS:
        if name not in source:
            raise ValueError(f"{src}: missing array {name}")
    if out.exists():
        shutil.rmtree(out)
    dest = zarr.open_group(str(out), mode="w", zarr_version=2)
    dest.attrs.update(dict(source.attrs))
    dest.attrs["source"] = (
        "pusht_cchi_v7_replay.zarr (Diffusion Policy, https://diffusion-policy.cs.columbia.edu/data/training/pusht.zip)"
    )
    # bit shuffle groups the slowly changing float bits together, which zstd compresses far better
    compressor = Blosc(cname="zstd", clevel=clevel, shuffle=Blosc.BITSHUFFLE)
    for name in tqdm(ARRAYS, desc="copy", unit="array", file=sys.stderr):
        values = np.asarray(source[name][...])
        array = dest.create_dataset(name, data=values, chunks=values.shape, compressor=compressor, dtype=values.dtype)
        if source[name].attrs:
            array.attrs.update(dict(source[name].attrs))
    check = zarr.open_group(str(out), mode="r")
    for name in ARRAYS:
        a, b = np.asarray(source[name][...]), np.asarray(check[name][...])
        if a.dtype != b.dtype or a.shape != b.shape or a.tobytes() != b.tobytes():
            raise ValueError(f"{out}: copy of {name} differs from the source")


if __name__ == "__main__":
    sys.exit(main())

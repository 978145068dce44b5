"""Download the full Push-T dataset (pusht.zip, with images) and extract its replay zarr store.

    python scripts/download_dataset.py                    # -> data/full/pusht_cchi_v7_replay.zarr
    python scripts/download_dataset.py --make-lowdim      # then rebuild data/pusht_lowdim.zarr from it

Streams the zip to a temporary folder beside DEST, optionally checks its SHA-256, extracts only
`pusht/pusht_cchi_v7_replay.zarr/` (rejecting absolute and `..` member paths), validates the store,
and only then moves it into place, so a failed run leaves nothing half-written behind.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import http.client
import importlib.util
import re
import shutil
import socket
import sys
import tempfile
import urllib.error
import urllib.parse
import urllib.request
import zipfile
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Callable, Iterator

import numpy as np
import zarr

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_URL = "https://diffusion-policy.cs.columbia.edu/data/training/pusht.zip"
DEFAULT_DEST = REPO_ROOT / "data" / "full"
DEFAULT_LOWDIM_OUT = REPO_ROOT / "data" / "pusht_lowdim.zarr"
STORE_NAME = "pusht_cchi_v7_replay.zarr"
ZIP_PREFIX = f"pusht/{STORE_NAME}/"
CHUNK_BYTES = 1 << 20


class DownloadError(Exception):
    """A problem that ends the run with a one-line message and exit code 2."""


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(
        description="Download pusht.zip, extract pusht/pusht_cchi_v7_replay.zarr into DEST and validate it.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--url", default=DEFAULT_URL, help="URL of pusht.zip (http, https or file)")
    parser.add_argument("--dest", type=Path, default=DEFAULT_DEST, help=f"folder that receives {STORE_NAME}")
    parser.add_argument("--sha256", type=_sha256_hex, default=None, help="expected SHA-256 of the zip (hex); checked if given")
    parser.add_argument("--force", action="store_true", help="download again even if a valid store is already at DEST")
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for the server on connect and on each read")
    parser.add_argument(
        "--make-lowdim", action="store_true", help="then write the low-dimensional copy (scripts/make_lowdim_dataset.py)"
    )
    parser.add_argument(
        "--lowdim-out", type=Path, default=DEFAULT_LOWDIM_OUT, help="output of --make-lowdim (replaced if it exists)"
    )
    args = parser.parse_args(argv)
    try:
        store = fetch_dataset(args.url, args.dest, sha256=args.sha256, force=args.force, timeout=args.timeout)
        if args.make_lowdim:
            make_lowdim(store, args.lowdim_out)
            print(f"wrote {args.lowdim_out}", file=sys.stderr)
    except (DownloadError, OSError) as exc:  # OSError: DEST not creatable or writable; its message names the path
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(store)
    return 0


def fetch_dataset(url: str, dest: Path, sha256: str | None = None, force: bool = False, timeout: float = 60.0) -> Path:
    """Return the path of a validated replay store in `dest`, downloading and extracting it unless already there."""
    store = dest / STORE_NAME
    if store.exists() and not force:
        try:
            validate_store(store)
        except DownloadError as exc:
            print(f"{store} is present but invalid ({exc}); downloading again", file=sys.stderr)
        else:
            print(f"{store} already present and valid; skipping the download (--force to redo)", file=sys.stderr)
            return store
    created = _missing_ancestor(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    # the work folder sits beside DEST so the final move is a rename on the same file system
    work = Path(tempfile.mkdtemp(prefix=f".{dest.name}.download-", dir=dest.parent))
    try:
        archive = work / "pusht.zip"
        digest = download(url, archive, timeout=timeout)
        print(f"sha256 {digest}", file=sys.stderr)
        if sha256 is not None and digest != sha256:
            raise DownloadError(f"{url}: SHA-256 mismatch (expected {sha256}, got {digest})")
        extracted = work / STORE_NAME
        extract_store(archive, extracted, source=url)
        validate_store(extracted, source=url)
        dest.mkdir(parents=True, exist_ok=True)
        if store.exists():
            shutil.rmtree(store)
        extracted.rename(store)
    except BaseException:
        # also on Ctrl-C: a DEST (and any parent) that this run created must not survive a failure
        if created is not None:
            shutil.rmtree(created, ignore_errors=True)
        raise
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return store


def download(url: str, target: Path, timeout: float = 60.0) -> str:
    """Stream `url` into `target` with a progress bar on stderr and return the SHA-256 (hex) of the bytes."""
    digest = hashlib.sha256()
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response, open(target, "wb") as out:
            length = response.headers.get("Content-Length")
            total = int(length) if length and length.isdigit() else None
            with _progress(total, desc=Path(urllib.parse.urlsplit(url).path).name or "download") as advance:
                for chunk in iter(lambda: response.read(CHUNK_BYTES), b""):
                    out.write(chunk)
                    digest.update(chunk)
                    advance(len(chunk))
            if total is not None and out.tell() != total:
                raise DownloadError(f"{url}: connection closed after {out.tell()} of {total} bytes")
    except urllib.error.HTTPError as exc:
        raise DownloadError(f"{url}: HTTP {exc.code} {exc.reason}") from None
    except urllib.error.URLError as exc:
        # urlopen wraps connect-phase failures (refused, DNS, connect timeout) in URLError
        reason = exc.reason
        if isinstance(reason, (socket.timeout, TimeoutError)):
            raise DownloadError(f"{url}: timed out after {timeout:g} s") from None
        raise DownloadError(f"{url}: cannot connect ({getattr(reason, 'strerror', None) or reason})") from None
    except (socket.timeout, TimeoutError):
        raise DownloadError(f"{url}: timed out after {timeout:g} s") from None
    except http.client.HTTPException as exc:  # e.g. IncompleteRead, a malformed status line
        raise DownloadError(f"{url}: bad HTTP response ({type(exc).__name__}: {exc})") from None
    except ValueError as exc:  # malformed URL or unknown scheme
        raise DownloadError(f"{url}: {exc}") from None
    except OSError as exc:
        raise DownloadError(f"{url}: {exc}") from None
    return digest.hexdigest()


def extract_store(archive: Path, out: Path, source: str | None = None) -> None:
    """Extract the `pusht/pusht_cchi_v7_replay.zarr/` members of `archive` into `out`, refusing unsafe member paths."""
    name = source or str(archive)
    try:
        with zipfile.ZipFile(archive) as zf:
            members = zf.infolist()
            # one unsafe name means a hostile or broken archive: refuse all of it, not just that member
            for info in members:
                if not _is_safe_member(info.filename):
                    raise DownloadError(f"{name}: unsafe member path {info.filename!r} (absolute or '..'); refusing to extract")
            wanted = [m for m in members if m.filename.startswith(ZIP_PREFIX) and not m.is_dir()]
            if not wanted:
                raise DownloadError(f"{name}: archive has no {ZIP_PREFIX} folder")
            root = out.resolve()
            with _progress(sum(m.file_size for m in wanted), desc="extract") as advance:
                for info in wanted:
                    target = (out / info.filename[len(ZIP_PREFIX) :]).resolve()
                    if root not in target.parents:
                        raise DownloadError(f"{name}: member {info.filename!r} escapes the destination")
                    target.parent.mkdir(parents=True, exist_ok=True)
                    with zf.open(info) as src, open(target, "wb") as dst:
                        shutil.copyfileobj(src, dst, CHUNK_BYTES)
                    advance(info.file_size)
    except zipfile.BadZipFile as exc:
        raise DownloadError(f"{name}: not a valid zip archive ({exc})") from None
    except (OSError, EOFError, NotImplementedError, zipfile.LargeZipFile) as exc:
        raise DownloadError(f"{name}: cannot extract ({exc})") from None


def validate_store(store: Path, source: str | None = None) -> None:
    """Check that `store` holds data/state (N x 5), data/action (N x 2) and increasing meta/episode_ends ending at N."""
    where = f"{source}: extracted store" if source else str(store)
    try:
        group = zarr.open_group(str(store), mode="r")
        for key in ("data/state", "data/action", "meta/episode_ends"):
            if key not in group or not isinstance(group[key], zarr.Array):
                raise DownloadError(f"{where}: missing array {key}")
        state = np.asarray(group["data/state"][...])
        action = np.asarray(group["data/action"][...])
        ends = np.asarray(group["meta/episode_ends"][...])
    except DownloadError:
        raise
    except Exception as exc:  # zarr raises many types for corrupt metadata or chunks; all mean "malformed"
        raise DownloadError(f"{where}: unreadable zarr store ({type(exc).__name__}: {exc})") from None
    n = state.shape[0] if state.ndim == 2 else -1
    if state.ndim != 2 or state.shape[1] != 5:
        raise DownloadError(f"{where}: data/state has shape {state.shape}, expected (N, 5)")
    if action.shape != (n, 2):
        raise DownloadError(f"{where}: data/action has shape {action.shape}, expected ({n}, 2)")
    if ends.ndim != 1 or ends.size == 0 or not np.issubdtype(ends.dtype, np.integer):
        raise DownloadError(f"{where}: meta/episode_ends must be a non-empty 1-D integer array, got {ends.dtype} {ends.shape}")
    if ends[0] <= 0 or np.any(np.diff(ends) <= 0):
        raise DownloadError(f"{where}: meta/episode_ends is not strictly increasing from above 0")
    if ends[-1] != n:
        raise DownloadError(f"{where}: meta/episode_ends ends at {ends[-1]}, but there are {n} frames")


def make_lowdim(store: Path, out: Path) -> None:
    """Write the low-dimensional copy of `store` to `out` with scripts/make_lowdim_dataset.py's copy_lowdim."""
    spec = importlib.util.spec_from_file_location("make_lowdim_dataset", Path(__file__).with_name("make_lowdim_dataset.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    try:
        module.copy_lowdim(store, out)
    except (ValueError, OSError) as exc:
        # copy_lowdim has already removed any previous `out`; a partial copy is worse than none
        shutil.rmtree(out, ignore_errors=True)
        raise DownloadError(f"{out}: low-dim copy failed ({exc})") from None


def _is_safe_member(name: str) -> bool:
    """True for a relative member path without `..`, drive letters or leading slashes (zip-slip guard)."""
    if not name or name.startswith(("/", "\\")) or PureWindowsPath(name).drive:
        return False
    return ".." not in PurePosixPath(name.replace("\\", "/")).parts


def _missing_ancestor(path: Path) -> Path | None:
    """The outermost ancestor of `path` (or `path` itself) that does not exist yet, i.e. what this run would create."""
    path = path.absolute()
    missing = None
    for candidate in (path, *path.parents):
        if candidate.exists():
            break
        missing = candidate
    return missing


@contextlib.contextmanager
def _progress(total: int | None, desc: str) -> Iterator[Callable[[int], object]]:
    """Yield an `advance(n_bytes)` callback drawing a tqdm bar on stderr, or doing nothing without tqdm."""
    try:
        from tqdm import tqdm
    except ImportError:
        yield lambda n: None
        return
    with tqdm(total=total, desc=desc, unit="B", unit_scale=True, unit_divisor=1024, file=sys.stderr) as bar:
        yield bar.update


def _sha256_hex(text: str) -> str:
    """argparse type: a 64-digit hex SHA-256, lower-cased."""
    if not re.fullmatch(r"[0-9a-fA-F]{64}", text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a 64-digit hex SHA-256")
    return text.lower()


if __name__ == "__main__":
    sys.exit(main())

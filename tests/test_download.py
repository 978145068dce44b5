"""scripts/download_dataset.py against a real HTTP server on 127.0.0.1 serving small pusht.zip look-alikes."""

from __future__ import annotations

import hashlib
import http.server
import importlib.util
import json
import socket
import subprocess
import sys
import threading
import zipfile
from pathlib import Path

import numpy as np
import pytest
import zarr

REPO = Path(__file__).resolve().parent.parent
SCRIPT = REPO / "scripts" / "download_dataset.py"
SOURCE = REPO / "data" / "pusht_lowdim.zarr"
ARRAYS = ("data/state", "data/action", "data/keypoint", "data/n_contacts", "meta/episode_ends")
PREFIX = "pusht/pusht_cchi_v7_replay.zarr/"

_spec = importlib.util.spec_from_file_location("download_dataset", SCRIPT)
download_dataset = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(download_dataset)


def _zip_store(path: Path, store: Path, prefix: str = PREFIX, extra: dict[str, bytes] | None = None) -> Path:
    """Zip every file of `store` under `prefix` (like pusht.zip does), plus `extra` raw members."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        for file in sorted(store.rglob("*")):
            if file.is_file():
                zf.write(file, prefix + file.relative_to(store).as_posix())
        for name, data in (extra or {}).items():
            zf.writestr(zipfile.ZipInfo(name), data)  # ZipInfo keeps the name verbatim, '..' and '/' included
    return path


def _broken_store(store: Path, drop: str | None = None, last_end_shift: int = 0) -> Path:
    """A copy of the source's state/action/episode_ends without array `drop`, last episode end shifted."""
    group = zarr.open_group(str(store), mode="w", zarr_version=2)
    source = zarr.open_group(str(SOURCE), mode="r")
    for name in ("data/state", "data/action", "meta/episode_ends"):
        if name != drop:
            values = source[name][...]
            if name == "meta/episode_ends":
                values[-1] += last_end_shift
            group.create_dataset(name, data=values)
    return store


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory):
    """Serve a folder of test archives over HTTP on a free loopback port; yields (base_url, request_log, folder)."""
    root = tmp_path_factory.mktemp("www")
    _zip_store(root / "pusht.zip", SOURCE)
    _zip_store(root / "slip.zip", SOURCE, extra={PREFIX + "../../evil.txt": b"owned"})
    _zip_store(root / "absolute.zip", SOURCE, extra={"/tmp/evil.txt": b"owned"})
    _zip_store(root / "nofolder.zip", SOURCE, prefix="other/replay.zarr/")
    broken = tmp_path_factory.mktemp("broken")
    _zip_store(root / "badends.zip", _broken_store(broken / "badends.zarr", last_end_shift=-1))
    _zip_store(root / "nostate.zip", _broken_store(broken / "nostate.zarr", drop="data/state"))
    (root / "notzip.zip").write_bytes(b"<html>this is not a zip</html>" * 100)
    log: list[str] = []

    class Handler(http.server.SimpleHTTPRequestHandler):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, directory=str(root), **kwargs)

        def do_GET(self):
            log.append(self.path)
            super().do_GET()

        def log_message(self, *args):  # keep pytest output clean
            pass

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}", log, root
    httpd.shutdown()
    httpd.server_close()


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=60)


def _assert_clean_failure(proc: subprocess.CompletedProcess, dest: Path, *words: str) -> None:
    """Exit 2, one `error:` line naming the problem, no traceback, and nothing left beside DEST."""
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, proc.stderr
    for word in words:
        assert word in errors[0], errors[0]
    assert not dest.exists()
    assert not list(dest.parent.glob(f".{dest.name}.download-*"))


def _assert_equal_to_source(store: Path, names=("data/state", "data/action", "meta/episode_ends")) -> None:
    got, want = zarr.open_group(str(store), mode="r"), zarr.open_group(str(SOURCE), mode="r")
    for name in names:
        a, b = np.asarray(got[name][...]), np.asarray(want[name][...])
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), name


def test_download_extract_validate_then_skip_then_force(server, tmp_path: Path) -> None:
    base, log, _ = server
    dest = tmp_path / "a" / "full"
    proc = _run("--url", f"{base}/pusht.zip", "--dest", str(dest))
    assert proc.returncode == 0, proc.stderr
    store = dest / "pusht_cchi_v7_replay.zarr"
    assert proc.stdout.strip() == str(store)
    _assert_equal_to_source(store, ARRAYS)
    assert not list(dest.parent.glob(".full.download-*"))

    requests = log.count("/pusht.zip")
    again = _run("--url", f"{base}/pusht.zip", "--dest", str(dest))
    assert again.returncode == 0 and again.stdout.strip() == str(store)
    assert "skipping" in again.stderr
    assert log.count("/pusht.zip") == requests  # the server never saw a second request

    forced = _run("--url", f"{base}/pusht.zip", "--dest", str(dest), "--force")
    assert forced.returncode == 0, forced.stderr
    assert log.count("/pusht.zip") == requests + 1
    _assert_equal_to_source(store, ARRAYS)


def test_sha256_is_checked(server, tmp_path: Path) -> None:
    base, _, root = server
    digest = hashlib.sha256((root / "pusht.zip").read_bytes()).hexdigest()
    bad = _run("--url", f"{base}/pusht.zip", "--dest", str(tmp_path / "bad"), "--sha256", "0" * 64)
    _assert_clean_failure(bad, tmp_path / "bad", "SHA-256 mismatch", f"{base}/pusht.zip", digest)
    good = _run("--url", f"{base}/pusht.zip", "--dest", str(tmp_path / "good"), "--sha256", digest.upper())
    assert good.returncode == 0, good.stderr


def test_http_404_names_the_url(server, tmp_path: Path) -> None:
    base, _, _ = server
    proc = _run("--url", f"{base}/missing.zip", "--dest", str(tmp_path / "full"))
    _assert_clean_failure(proc, tmp_path / "full", f"{base}/missing.zip", "HTTP 404")


@pytest.mark.parametrize("archive", ["slip.zip", "absolute.zip"])
def test_zip_slip_member_is_rejected(server, tmp_path: Path, archive: str) -> None:
    base, _, _ = server
    dest = tmp_path / "x" / "y" / "full"
    proc = _run("--url", f"{base}/{archive}", "--dest", str(dest))
    _assert_clean_failure(proc, dest, "unsafe member path")
    assert not list(tmp_path.rglob("evil.txt"))
    assert not (tmp_path / "x").exists()  # the parents this run created are gone too


def test_make_lowdim_reproduces_the_source(server, tmp_path: Path) -> None:
    base, _, _ = server
    out = tmp_path / "lowdim.zarr"
    proc = _run("--url", f"{base}/pusht.zip", "--dest", str(tmp_path / "full"), "--make-lowdim", "--lowdim-out", str(out))
    assert proc.returncode == 0, proc.stderr
    _assert_equal_to_source(out, ARRAYS)
    assert json.loads((out / ".zattrs").read_text())["source"].startswith("pusht_cchi_v7_replay.zarr")


@pytest.mark.parametrize(
    ("archive", "problem"),
    [
        ("notzip.zip", "not a valid zip archive"),
        ("nofolder.zip", "has no pusht/pusht_cchi_v7_replay.zarr/ folder"),
        ("badends.zip", "episode_ends ends at 25649, but there are 25650 frames"),
        ("nostate.zip", "missing array data/state"),
    ],
)
def test_bad_archives_fail_cleanly(server, tmp_path: Path, capsys, archive: str, problem: str) -> None:
    base, _, _ = server
    dest = tmp_path / "full"
    assert download_dataset.main(["--url", f"{base}/{archive}", "--dest", str(dest)]) == 2
    err = capsys.readouterr().err
    line = next(line for line in err.splitlines() if line.startswith("error:"))
    assert f"{base}/{archive}" in line and problem in line
    assert not dest.exists() and not list(tmp_path.glob(".full.download-*"))


def test_connection_refused_and_timeout(tmp_path: Path, capsys) -> None:
    with socket.socket() as sock:  # a port that was free a moment ago: nothing listens there now
        sock.bind(("127.0.0.1", 0))
        closed_port = sock.getsockname()[1]
    url = f"http://127.0.0.1:{closed_port}/pusht.zip"
    assert download_dataset.main(["--url", url, "--dest", str(tmp_path / "full")]) == 2
    assert f"error: {url}: cannot connect" in capsys.readouterr().err

    # the kernel completes the handshake for a listening socket that never accepts, so the reply never comes
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(1)
        url = f"http://127.0.0.1:{silent.getsockname()[1]}/pusht.zip"
        assert download_dataset.main(["--url", url, "--dest", str(tmp_path / "full"), "--timeout", "0.5"]) == 2
    assert f"error: {url}: timed out after 0.5 s" in capsys.readouterr().err
    assert not (tmp_path / "full").exists()


def test_existing_invalid_store_is_replaced(server, tmp_path: Path) -> None:
    base, _, _ = server
    store = tmp_path / "full" / "pusht_cchi_v7_replay.zarr"
    store.mkdir(parents=True)
    (store / ".zgroup").write_text('{"zarr_format": 2}')
    proc = _run("--url", f"{base}/pusht.zip", "--dest", str(tmp_path / "full"))
    assert proc.returncode == 0, proc.stderr
    assert "present but invalid" in proc.stderr
    _assert_equal_to_source(store, ARRAYS)

"""`python -m service [--host H] [--port P]`: serve with connection-level limits (what `make serve` and Docker run).

Reads the `PUSHT_*` settings (a bad one: one line naming it, exit 2), fits PUSHT_MAX_CONNECTIONS
under the file-descriptor limit, and runs uvicorn with service.protocol's header deadline and caps,
PUSHT_KEEP_ALIVE_S for idle connections and PUSHT_SHUTDOWN_TIMEOUT_S for a bounded shutdown.
"""

from __future__ import annotations

import argparse
import sys

from service import protocol
from service.settings import SettingsError, load_settings

RESERVED_FDS = 64
"""File descriptors kept for model files, logs, threads and the listening socket."""


def fit_connections(wanted: int) -> int:
    """`wanted`, lowered so that that many open sockets stay within the soft RLIMIT_NOFILE."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    except (ImportError, OSError, ValueError):
        return wanted
    if soft == resource.RLIM_INFINITY:
        return wanted
    return max(1, min(wanted, soft - RESERVED_FDS))


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: every interface)")
    parser.add_argument("--port", type=int, default=8000, help="TCP port")
    parser.add_argument(
        "--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"), help="uvicorn log level"
    )
    args = parser.parse_args(argv)
    try:
        settings = load_settings()
    except SettingsError as exc:
        print(f"cannot start: {exc}", file=sys.stderr)
        return 2
    import uvicorn

    connections = fit_connections(settings.max_connections)
    if connections < settings.max_connections:
        print(
            f"PUSHT_MAX_CONNECTIONS lowered from {settings.max_connections} to {connections} to fit the open-file limit "
            f"(raise it with `ulimit -n`)",
            file=sys.stderr,
        )
    protocol.ENTRY_POINT = True
    uvicorn.run(
        "service.app:app",
        host=args.host,
        port=args.port,
        log_level=args.log_level,
        access_log=settings.access_log,
        http=protocol.hardened_protocol(settings.max_header_bytes, settings.header_timeout_s, connections),
        timeout_keep_alive=settings.keep_alive_s,  # type: ignore[arg-type]  # uvicorn takes seconds, float is fine
        timeout_graceful_shutdown=settings.shutdown_timeout_s,  # type: ignore[arg-type]
        h11_max_incomplete_event_size=settings.max_header_bytes,
        # websocket frames bounded like HTTP bodies (closed with 1009 beyond), and no per-message compression, whose
        # small frames would inflate past any limit checked after decompression
        ws_max_size=settings.max_body_bytes,
        ws_per_message_deflate=False,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

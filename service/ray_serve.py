"""`python -m service.ray_serve --replicas N --port P`: the same app behind Ray Serve, in N replicas.

Starts a local Ray cluster, or joins the one at RAY_ADDRESS, and deploys `service.app.create_app()` as
a Serve FastAPI ingress with N replicas; each replica loads the policies in its lifespan and batches
the requests it gets, and Ray's HTTP proxy on --host:--port spreads requests over the replicas. The
PUSHT_* settings go to the replicas; their nodes need this package and the models at PUSHT_MODELS_DIR.
Needs the ray extra (`pip install -e ".[ray]"`); the Docker image has no Ray.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any, Awaitable, Callable

__all__ = ["build_app", "main"]

APP_NAME = "pusht"
REPLICA_HEADER = b"x-pusht-replica"
"""Response header naming the replica (host:pid) that answered, so a client can see the load spread."""


def build_app() -> Any:
    """The service app for this replica's PUSHT_* settings, tagging each response with the replica."""
    from service.app import create_app
    from service.settings import load_settings

    app = create_app(load_settings())
    app.add_middleware(ReplicaHeader, name=f"{os.uname().nodename}:{os.getpid()}")
    return app


class ReplicaHeader:
    """ASGI middleware adding `x-pusht-replica: HOST:PID` to every HTTP response."""

    def __init__(self, app: Callable, name: str) -> None:
        self.app = app
        self.header = (REPLICA_HEADER, name.encode())

    async def __call__(self, scope: dict, receive: Callable, send: Callable[[dict], Awaitable[None]]) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def tagged(message: dict) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", []), self.header]}
            await send(message)

        await self.app(scope, receive, tagged)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = _parser()
    args = parser.parse_args(argv)
    if args.replicas < 1:
        parser.error("--replicas must be at least 1")
    try:
        import ray
        from ray import serve
    except ImportError:
        print("cannot start: service.ray_serve needs Ray Serve: pip install -e '.[ray]'", file=sys.stderr)
        return 2
    from service.ray_serve import build_app as builder  # by its module's name, not __main__, so replicas import it
    from service.settings import SettingsError, load_settings

    try:
        settings = load_settings()  # a bad PUSHT_ variable: one line here, not one per replica
    except SettingsError as exc:
        print(f"cannot start: {exc}", file=sys.stderr)
        return 2
    env = {k: v for k, v in os.environ.items() if k.startswith("PUSHT_")}
    env["PUSHT_MODELS_DIR"] = str(Path(settings.models_dir).resolve())
    address = os.environ.get("RAY_ADDRESS")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no usage reports leave this machine
    _init_ray(ray, args, env, address)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        serve.start(http_options={"host": args.host, "port": args.port})
        deployment = serve.deployment(
            serve.ingress(builder)(),
            name="PushTService",
            num_replicas=args.replicas,
            ray_actor_options={"num_cpus": args.replica_cpus, "runtime_env": {"env_vars": env}},
        )
        serve.run(deployment.bind(), name=APP_NAME, route_prefix="/")
        where = f"the Ray cluster at {address}" if address else "a local Ray cluster"
        print(
            f"ready: {args.replicas} replicas of the service from {env['PUSHT_MODELS_DIR']} on {where}, "
            f"http://{args.host}:{args.port} (Ctrl-C stops)",
            flush=True,
        )
        while not stop.wait(1.0):
            pass
    finally:
        if address:  # someone else's cluster: take only our app off it
            serve.delete(APP_NAME)
        # A local cluster goes with its processes, replicas included (serve.shutdown would wait on them,
        # and hang if Ctrl-C already reached them).
        ray.shutdown()
        print("stopped", flush=True)
    return 0


def _init_ray(ray: Any, args: argparse.Namespace, env: dict[str, str], address: str | None) -> None:
    """Join the cluster at `address`, or start a local one sized by the command line."""
    if address:
        ray.init(address=address, runtime_env={"env_vars": env}, log_to_driver=False)
    else:
        # address="local": a new cluster, even where `ray start` left a record of an older one.
        ray.init(
            address="local",
            num_cpus=args.local_cpus or os.cpu_count(),
            object_store_memory=args.object_store_mb << 20,
            include_dashboard=False,
            runtime_env={"env_vars": env},
            log_to_driver=False,
        )


def _parser() -> argparse.ArgumentParser:
    """The command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--replicas", type=int, default=1, help="replicas of the service (each loads every policy)")
    parser.add_argument("--host", default="127.0.0.1", help="address of Ray Serve's HTTP proxy (0.0.0.0: every interface)")
    parser.add_argument("--port", type=int, default=8000, help="TCP port of Ray Serve's HTTP proxy")
    parser.add_argument("--replica-cpus", type=float, default=1.0, help="CPUs each replica reserves in the Ray cluster")
    parser.add_argument(
        "--local-cpus",
        type=int,
        default=None,
        help="CPUs of the local cluster (default: this machine's); ignored with RAY_ADDRESS",
    )
    parser.add_argument(
        "--object-store-mb",
        type=int,
        default=100,
        help="object store of the local cluster (requests are small); ignored with RAY_ADDRESS",
    )
    return parser


if __name__ == "__main__":
    sys.exit(main())

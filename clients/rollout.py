"""Roll out a served Push-T policy over HTTP and print its score as one JSON line.

    python clients/rollout.py --url http://127.0.0.1:8000 --policy flow --episodes 100 --num-envs 100
    python clients/rollout.py --url http://127.0.0.1:8000      # the service's default policy

K envs step in lockstep with the project's one rollout runner (`pusht.rollout.run_episodes`); each
decision step sends ONE batched `POST /act` for every env still running, and each returned chunk is
executed open loop for --action-horizon steps (default: the policy's chunk length, from `GET /policies`). Reproducible: episode i is reset with seed
`--seed + i`, and its decision d sends, in that request's `seeds`, the row seed
`pusht.rollout.decision_seed(--seed + i, d)`, from which the service draws that row's flow noise;
`python -m training.evaluate` applies the same rules in process, so the same model gives the same
episodes both ways, whatever --num-envs. `--out FILE` writes one JSON line per episode.

Imports only the standard library, numpy, httpx, tqdm, Pillow (for --gif) and `pusht`: no torch.
Errors (unreachable server, timeout, 4xx/5xx answer, bad URL) end with one line on stderr and exit 2.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable
from urllib.parse import urlsplit

import httpx
import numpy as np

if importlib.util.find_spec("pusht") is None:
    # Run as a script from a checkout that was not pip-installed: the repo root holds `pusht`.
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from pusht.gif import FPS, annotated_frame
from pusht.gif import write_gif as _write_gif
from pusht.results import add_output_arguments
from pusht.rollout import RolloutSummary, card_id, check_output_path, episode_seeds, run_episodes, write_episode_records
from pusht.spec import HELD_OUT_SEED

EXIT_ERROR = 2
_DETAIL_CHARS = 300


class ClientError(Exception):
    """A failure to report as one line on stderr (no traceback)."""


class HttpPolicy:
    """The runner's act function over HTTP: one `POST /act` per call, on one keep-alive connection."""

    def __init__(
        self,
        url: str,
        policy: str | None,
        api_key: str | None = None,
        timeout: float = 30.0,
        on_response: Callable[[int, float], None] | None = None,
    ):
        self.endpoint = act_endpoint(url)
        self.policy = policy
        self.on_response = on_response
        headers = {"X-API-Key": api_key} if api_key else {}
        self.client = httpx.Client(headers=headers, timeout=httpx.Timeout(timeout))
        self.latencies_s: list[float] = []

    def __call__(self, states: np.ndarray, seeds: list[int]) -> np.ndarray:
        """POST the batch of states with one seed per row; return actions float32 [B, horizon, 2]."""
        # float32 -> Python float -> JSON is exact, so the server sees the same float32 states.
        payload = {
            "policy": self.policy,
            "states": np.asarray(states, dtype=np.float32).tolist(),
            "seeds": [int(s) for s in seeds],
        }
        start = time.perf_counter()
        response = self._send("POST", self.endpoint, json=payload)
        self.latencies_s.append(time.perf_counter() - start)
        try:
            actions = np.asarray(response.json()["actions"], dtype=np.float32)
        except (ValueError, TypeError, KeyError) as exc:
            raise ClientError(
                f"POST {self.endpoint} -> {response.status_code}, but the answer has no numeric 'actions' array "
                f"({type(exc).__name__}: {_one_line(exc)}): {_one_line(response.text)[:_DETAIL_CHARS]}"
            ) from None
        if self.on_response is not None:
            self.on_response(self.requests, self.latencies_s[-1])
        return actions

    def info(self) -> dict[str, Any]:
        """The served policy's entry of `GET /policies`: kind, horizon, git_commit, steps, ...; no policy named: the default's."""
        url = self.endpoint[: -len("/act")] + "/policies"
        response = self._send("GET", url)
        try:
            info = {p["name"]: p for p in response.json()["policies"]}
        except (ValueError, TypeError, KeyError) as exc:
            raise ClientError(f"GET {url}: unexpected answer ({type(exc).__name__}: {_one_line(exc)})") from None
        if self.policy is None:
            self.policy = next((name for name, p in info.items() if p.get("default")), None)
            if self.policy is None:
                raise ClientError(f"GET {url}: no policy is marked default; name one with --policy (it has {sorted(info)})")
        if self.policy not in info:
            raise ClientError(f"GET {url}: the service has no policy {self.policy!r} (it has {sorted(info)})")
        return info[self.policy]

    def _send(self, method: str, url: str, **kwargs: Any) -> httpx.Response:
        """One request on the connection; a transport failure or a 4xx/5xx answer as a ClientError."""
        try:
            response = self.client.request(method, url, **kwargs)
        except httpx.TimeoutException as exc:
            raise ClientError(
                f"{method} {url} timed out after {self.client.timeout.read} s ({_one_line(exc) or type(exc).__name__})"
            ) from None
        except httpx.ConnectError as exc:
            raise ClientError(f"cannot connect to {url}: {_one_line(exc) or 'connection failed'}") from None
        except httpx.HTTPError as exc:
            raise ClientError(f"{method} {url} failed: {type(exc).__name__}: {_one_line(exc)}") from None
        if response.status_code >= 400:
            raise ClientError(f"{method} {url} -> {response.status_code} {response.reason_phrase}: {_error_detail(response)}")
        return response

    @property
    def requests(self) -> int:
        """Number of answered requests."""
        return len(self.latencies_s)

    def close(self) -> None:
        """Close the HTTP connection."""
        self.client.close()


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: roll out, print one JSON line on stdout; errors as one line on stderr."""
    args = vars(_parser().parse_args(argv))
    args["progress"] = not args.pop("no_progress")
    try:
        report = rollout(RolloutOptions(**args))
    # ValueError: the runner's and path checks (bad arguments, malformed actions from the server); OSError: unwritable files
    except (ClientError, ValueError, OSError) as exc:
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    print(json.dumps(report))
    return 0


@dataclass
class RolloutOptions:
    """The client's options (its command line): `policy` None: the service's default policy; `action_horizon` None: the
    policy's whole chunk (its horizon in `GET /policies`); with `out`, one JSON line per episode goes there; with `gif`,
    the first episode."""

    url: str
    policy: str | None = None
    episodes: int = 100
    num_envs: int = 100
    seed: int = HELD_OUT_SEED
    max_steps: int = 300
    action_horizon: int | None = None
    gif: str | Path | None = None
    api_key: str | None = None
    timeout: float = 30.0
    progress: bool = True
    out: str | Path | None = None


def rollout(options: RolloutOptions) -> dict[str, Any]:
    """Play episodes seed..seed+episodes-1 against the service at `options.url`; return the JSON report (paths on stderr)."""
    url, policy, episodes, num_envs, seed = options.url, options.policy, options.episodes, options.num_envs, options.seed
    max_steps, action_horizon, timeout, gif, out = (
        options.max_steps,
        options.action_horizon,
        options.timeout,
        options.gif,
        options.out,
    )
    for name, value in (
        ("episodes", episodes),
        ("num_envs", num_envs),
        ("max_steps", max_steps),
        ("action_horizon", 1 if action_horizon is None else action_horizon),
    ):
        if value < 1:
            raise ClientError(f"--{name.replace('_', '-')} must be at least 1, got {value}")
    if not timeout > 0:
        raise ClientError(f"--timeout must be positive, got {timeout}")
    if seed < 0:
        raise ClientError(f"--seed must be non-negative, got {seed}")
    # the paths are checked before the rollout, not after minutes of it
    gif = check_output_path("--gif", gif) if gif is not None else None
    out = check_output_path("--out", out) if out is not None else None
    seeds = episode_seeds(seed, episodes)
    bar = _ProgressBar(len(seeds)) if options.progress else None
    act = HttpPolicy(url, policy, api_key=options.api_key, timeout=timeout, on_response=bar.on_response if bar else None)
    try:
        info = act.info()
        policy = act.policy
        horizon = info.get("horizon")  # None from a service that does not list it: the runner takes the chunks' length
        if action_horizon is not None and horizon is not None and action_horizon > horizon:
            raise ClientError(f"--action-horizon {action_horizon} exceeds policy {policy!r}'s chunks of {horizon} actions")
        summary = run_episodes(
            act,
            seeds,
            num_envs=num_envs,
            max_steps=max_steps,
            action_horizon=action_horizon or horizon,
            progress=bar if bar is not None else False,
            record_frames=annotated_frame if gif is not None else False,
        )
    finally:
        act.close()
        if bar is not None:
            bar.close()
    if out is not None:
        write_episode_records(out, summary, policy, card_id(policy, info.get("git_commit"), info.get("steps")))
        print(f"episodes: wrote {len(summary.episodes)} lines to {out}", file=sys.stderr)
    if gif is not None:
        write_gif(summary.frames, gif)
        print(f"gif: wrote {gif} ({len(summary.frames)} frames at {FPS} fps, real speed)", file=sys.stderr)
    return report(summary, act, url=url, policy=policy)


def report(summary: RolloutSummary, act: HttpPolicy, url: str, policy: str) -> dict[str, Any]:
    """The one-line JSON report: scores with their 95% bootstrap intervals, seeds, timing, request stats."""
    latencies_ms = np.asarray(act.latencies_s, dtype=np.float64) * 1000.0
    return {
        "policy": policy,
        "url": url,
        **summary.scores(),
        "requests": act.requests,
        "mean_request_latency_ms": round(float(latencies_ms.mean()), 2) if act.requests else None,
        "p95_request_latency_ms": round(float(np.percentile(latencies_ms, 95)), 2) if act.requests else None,
    }


def act_endpoint(url: str) -> str:
    """The `/act` URL of a service base URL (a URL that already ends in /act is kept)."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.netloc:
        raise ClientError(f"--url must be an http:// or https:// URL with a host, e.g. http://127.0.0.1:8000; got {url!r}")
    base = url.rstrip("/")
    return base if parts.path.rstrip("/").endswith("/act") else f"{base}/act"


def write_gif(frames: list[np.ndarray], path: str | Path) -> None:
    """Write every recorded frame as a looping GIF at the control rate (real speed)."""
    try:
        _write_gif(frames, path)
    except (OSError, ValueError) as exc:
        raise ClientError(f"cannot write the GIF {path}: {_one_line(exc)}") from None


class _HelpFormatter(argparse.HelpFormatter):
    """Shows a flag's default once, and none for required flags, empty defaults or switches."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.required or action.default in (None, False, "", argparse.SUPPRESS):
            return text
        return text + " (default: %(default)s)"


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python clients/rollout.py",
        description=(
            "Roll out a served Push-T policy over HTTP: K envs in lockstep, one batched POST /act per "
            "decision step, each action chunk executed open loop. Prints ONE JSON line with the scores. "
            "Episode i uses env seed SEED+i; its decision d sends row seed pusht.rollout.decision_seed(SEED+i, d) "
            "in the request's seeds, so the same command gives the same episodes, whatever --num-envs."
        ),
        formatter_class=_HelpFormatter,
    )
    parser.add_argument("--url", required=True, help="base URL of the service, e.g. http://127.0.0.1:8000")
    parser.add_argument(
        "--policy", default=None, help="policy name served by the service (default: its default policy, GET /policies)"
    )
    parser.add_argument("--episodes", type=int, default=100, help="number of episodes, env seeds SEED..SEED+N-1")
    parser.add_argument(
        "--num-envs",
        type=int,
        default=100,
        help="envs stepped in lockstep, one request per decision for all; scores do not depend on it",
    )
    parser.add_argument(
        "--seed", type=int, default=HELD_OUT_SEED, help=f"first episode seed ({HELD_OUT_SEED}.. are the held-out seeds)"
    )
    parser.add_argument("--max-steps", type=int, default=300, help="episode step limit")
    parser.add_argument(
        "--action-horizon",
        type=int,
        default=None,
        help="actions of each chunk executed open loop (default: the whole chunk, the policy's horizon in GET /policies)",
    )
    add_output_arguments(parser)
    parser.add_argument("--api-key", default=None, help="sent as the X-API-Key header when the service requires a key")
    parser.add_argument("--timeout", type=float, default=30.0, metavar="SECONDS", help="per-request timeout in seconds")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    return parser


class _ProgressBar:
    """A tqdm bar of finished episodes on stderr, with the request count and latency as its postfix.

    Opened at the first answered request, so that an error there prints its one line and nothing else;
    the postfix moves at every request because in lockstep most episodes end together at the step limit.
    """

    def __init__(self, total: int) -> None:
        self.total = total
        self.bar = None

    def _open(self):
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=self.total, desc="episodes", unit="ep", file=sys.stderr, leave=False)
        return self.bar

    def __call__(self, done: int, total: int) -> None:
        bar = self._open()
        bar.n = done
        bar.refresh()

    def on_response(self, requests: int, latency_s: float) -> None:
        self._open().set_postfix(requests=requests, latency_ms=f"{latency_s * 1000:.1f}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _error_detail(response: httpx.Response) -> str:
    try:
        detail = response.json().get("detail", response.json())
    except (ValueError, AttributeError):
        return _one_line(response.text)[:_DETAIL_CHARS] or "(empty body)"
    if isinstance(detail, list):  # FastAPI validation errors: [{"loc": [...], "msg": ...}, ...]
        detail = "; ".join(
            f"{'.'.join(str(p) for p in d.get('loc', []))}: {d.get('msg', d)}" if isinstance(d, dict) else str(d) for d in detail
        )
    elif not isinstance(detail, str):
        detail = json.dumps(detail)
    return _one_line(detail)[:_DETAIL_CHARS]


def _one_line(value: Any) -> str:
    return " ".join(str(value).split())


if __name__ == "__main__":
    sys.exit(main())

"""The lifecycle of one run folder, shared by every training loop (training.train, training.finetune).

    run = Run.start(out_dir, name, config, resume=args.resume, overwrite=args.overwrite, is_main=rank == 0)
    state = run.load_state()             # None on a fresh start; on --resume (step, tensors, extra)
    for step in range(first, steps + 1):
        ...                              # one update
        run.log({"type": "train", "step": step, "loss": loss})     # OUT_DIR/NAME/log.jsonl
        if step % every == 0 or run.stop_requested:                # periodic, and on SIGTERM/SIGINT
            run.save_state(step, tensors, extra)                   # state.json + state-STEP.safetensors
        if run.stop_requested:
            break                        # then exit with run.exit_code(): 128 + the signal number
    else:
        run.finish()                     # every step ran: state.json says finished, the big state file goes
    run.close()                          # (or `with Run.start(...) as run:`) gives SIGTERM/SIGINT back

`run.dir` is the folder, `run.records` the log so far (reloaded on resume), `run.elapsed_s` the wall
time over all starts (for cards).

Call `Run.start` after the loop's own setup (data, model) has succeeded, so a failed start leaves the
disk as it was; `Run.start` checks everything before it writes. It refuses an existing folder (one line,
`RunError`, the loop exits 2) unless `resume` (the saved config must equal `config` except the keys in
`may_change`) or `overwrite` (only a folder holding a config.json is removed). It prints the config and
saves it as config.json. Resumable state is safetensors + JSON only, never pickle: `tensors` holds
weights, optimizer moments (`pack_optimizer`) and RNG states (`pack_rng`, as tensors); `extra` any JSON.
The JSON file is written last, so a SIGKILL mid-save leaves the previous state intact. With
`interruptible()` around a long phase (an evaluation), a signal ends that phase at once (`RunStopped`).
On ranks other than the main one (`is_main=False`) nothing is checked or written; signals still count.
"""

from __future__ import annotations

import contextlib
import json
import random
import shutil
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch

from policies.checkpoint import read_tensors, write_tensors, write_text_atomic

STATE_FILE = "state.json"
CONFIG_FILE = "config.json"
LOG_FILE = "log.jsonl"
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class RunError(ValueError):
    """A run folder cannot be started, resumed or read; the message names it."""


class RunStopped(BaseException):
    """Raised inside `Run.interruptible()` when SIGTERM/SIGINT arrives (a BaseException, so broad handlers let it pass)."""


class Run:
    """One run folder: config, log, resumable state and the stop signals; see the module docstring."""

    def __init__(
        self,
        run_dir: Path,
        config: dict[str, Any],
        is_main: bool,
        resumed: bool,
        records: list[dict[str, Any]],
        state: dict[str, Any] | None,
    ) -> None:
        self.dir, self.config, self.is_main, self.resumed, self.records = run_dir, config, is_main, resumed, records
        self._state = state  # the saved state.json (resume), else None
        self._clock = time.perf_counter()
        self.stop_signal: str | None = None
        self._raise_on_signal = False
        self._previous_handlers: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():
            for signum in STOP_SIGNALS:
                self._previous_handlers[signum] = signal.signal(signum, self._on_signal)

    @classmethod
    def start(
        cls,
        out_dir: str | Path,
        name: str,
        config: dict[str, Any],
        *,
        resume: bool = False,
        overwrite: bool = False,
        is_main: bool = True,
        may_change: tuple[str, ...] = ("progress", "threads"),
    ) -> Run:
        """Check, then create or reopen OUT_DIR/NAME; RunError (nothing written) if it may not be used."""
        if not name or name in (".", "..") or "/" in name or "\\" in name:
            raise RunError(f"run name {name!r} must be a plain folder name (no slashes)")
        run_dir = Path(out_dir) / name
        if resume and overwrite:
            raise RunError("--resume and --overwrite exclude each other")
        if not is_main:
            return cls(run_dir, config, False, resume, [], _read_state(run_dir) if resume else None)
        exists = run_dir.exists() and (not run_dir.is_dir() or any(run_dir.iterdir()))
        state = None
        if resume:
            state = _check_resumable(run_dir, config, may_change)
        elif exists and not overwrite:
            raise RunError(
                f"{run_dir} already exists: choose another --name, or pass --resume to continue it or --overwrite to replace it"
            )
        elif exists and not (run_dir / CONFIG_FILE).is_file():
            raise RunError(f"{run_dir} is not a run folder (no {CONFIG_FILE}); --overwrite removes run folders only")
        json.dumps(config, allow_nan=False)  # a config that cannot be saved fails before anything is written

        if resume:
            # log records after the saved step belong to steps that will run again
            records = [r for r in _read_log(run_dir) if r.get("step", 0) <= state["step"]]
            write_text_atomic(run_dir / LOG_FILE, "".join(json.dumps(r) + "\n" for r in records))
        else:
            if exists:
                shutil.rmtree(run_dir)
            run_dir.mkdir(parents=True, exist_ok=True)
            write_text_atomic(run_dir / CONFIG_FILE, json.dumps(config, indent=2) + "\n")
            (run_dir / LOG_FILE).write_text("")
            records = []
        print(f"config: {json.dumps(config)}", file=sys.stderr)
        verb = f"resumed at step {state['step']}" if resume else ("replaced" if exists else "created")
        print(f"run dir: {run_dir} ({verb})", file=sys.stderr)
        return cls(run_dir, config, True, resume, records, state)

    @property
    def stop_requested(self) -> bool:
        """True once SIGTERM or SIGINT has arrived."""
        return self.stop_signal is not None

    def exit_code(self) -> int:
        """0, or 128 + the signal number after a stop (the shell's convention)."""
        return 128 + int(getattr(signal, self.stop_signal)) if self.stop_signal else 0

    @property
    def elapsed_s(self) -> float:
        """Wall time of this run over all its starts."""
        before = self._state["elapsed_s"] if self._state else 0.0
        return before + time.perf_counter() - self._clock

    def log(self, record: dict[str, Any]) -> None:
        """Append one JSON record to log.jsonl (and to `records`)."""
        if not self.is_main:
            return
        self.records.append(record)
        with (self.dir / LOG_FILE).open("a") as handle:
            handle.write(json.dumps(record) + "\n")

    def save_state(self, step: int, tensors: dict[str, torch.Tensor], extra: dict[str, Any] | None = None) -> None:
        """Write the resumable state of `step`: tensors as safetensors, `extra` as JSON (written last: the commit)."""
        if not self.is_main:
            return
        name = f"state-{step:09d}.safetensors"
        write_tensors(self.dir / name, tensors)
        record = {"step": step, "file": name, "elapsed_s": self.elapsed_s, "finished": False, "extra": extra or {}}
        write_text_atomic(self.dir / STATE_FILE, json.dumps(record, indent=2, allow_nan=False) + "\n")
        self._drop_state_files(keep=name)

    def load_state(self) -> tuple[int, dict[str, torch.Tensor], dict[str, Any]] | None:
        """(step, tensors, extra) of the saved state when resuming, else None."""
        if not self.resumed:
            return None
        tensors, _ = read_tensors(self.dir / self._state["file"], "resumable state")
        return self._state["step"], tensors, self._state["extra"]

    def finish(self, step: int | None = None, extra: dict[str, Any] | None = None) -> None:
        """Mark the run finished at `step` (default: the last logged step) and remove the big state file; restores signal handlers."""
        if step is None:
            step = max((r["step"] for r in self.records if isinstance(r.get("step"), int)), default=0)
        if self.is_main:
            record = {"step": step, "file": None, "elapsed_s": self.elapsed_s, "finished": True, "extra": extra or {}}
            write_text_atomic(self.dir / STATE_FILE, json.dumps(record, indent=2, allow_nan=False) + "\n")
            self._drop_state_files(keep=None)
        self.close()

    @contextlib.contextmanager
    def interruptible(self) -> Iterator[None]:
        """Inside this block a stop signal raises RunStopped at once instead of waiting for the loop."""
        if self.stop_requested:
            raise RunStopped(self.stop_signal)
        self._raise_on_signal = True
        try:
            yield
        finally:
            self._raise_on_signal = False

    def close(self) -> None:
        """Give SIGTERM/SIGINT back to their previous handlers."""
        for signum, handler in self._previous_handlers.items():
            signal.signal(signum, handler)
        self._previous_handlers = {}

    def __enter__(self) -> Run:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _on_signal(self, signum: int, frame: Any) -> None:
        if self.stop_requested:
            # a second signal: the user insists, so give up on the orderly stop
            self.close()
            raise KeyboardInterrupt
        self.stop_signal = signal.Signals(signum).name
        if self.is_main:
            print(f"\n{self.stop_signal}: saving a resumable checkpoint, then stopping (again to abort)", file=sys.stderr)
        if self._raise_on_signal:
            raise RunStopped(self.stop_signal)

    def _drop_state_files(self, keep: str | None) -> None:
        for path in self.dir.glob("state-*.safetensors*"):
            if path.name != keep:
                path.unlink(missing_ok=True)


def pack_optimizer(optimizer: torch.optim.Optimizer, prefix: str = "optimizer") -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """An optimizer's state_dict as tensors (moments, step counts) and JSON (param groups, other values)."""
    state_dict = optimizer.state_dict()
    tensors, other = {}, {}
    for index, values in state_dict["state"].items():
        for key, value in values.items():
            if isinstance(value, torch.Tensor):
                tensors[f"{prefix}.{index}.{key}"] = value
            else:
                other[f"{index}.{key}"] = value
    return tensors, {"param_groups": state_dict["param_groups"], "other": other}


def unpack_optimizer(
    optimizer: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], extra: dict[str, Any], prefix: str = "optimizer"
) -> None:
    """Load what `pack_optimizer` produced back into `optimizer`."""
    state: dict[int, dict[str, Any]] = {}
    for name, value in tensors.items():
        if name.startswith(prefix + "."):
            index, key = name[len(prefix) + 1 :].split(".", 1)
            state.setdefault(int(index), {})[key] = value
    for name, value in extra["other"].items():
        index, key = name.split(".", 1)
        state.setdefault(int(index), {})[key] = value
    optimizer.load_state_dict({"state": state, "param_groups": extra["param_groups"]})


def pack_rng(generators: dict[str, torch.Generator] | None = None, prefix: str = "rng") -> dict[str, torch.Tensor]:
    """The torch, numpy and Python global RNG states, and those of named torch generators, as tensors."""
    _, key, pos, has_gauss, gauss = np.random.get_state()
    version, python_state, python_gauss = random.getstate()
    tensors = {
        f"{prefix}.torch": torch.get_rng_state(),
        f"{prefix}.numpy.key": torch.from_numpy(key.astype(np.int64)),
        f"{prefix}.numpy.pos": torch.tensor([pos, has_gauss], dtype=torch.int64),
        f"{prefix}.numpy.gauss": torch.tensor([gauss], dtype=torch.float64),
        f"{prefix}.python.state": torch.tensor(python_state, dtype=torch.int64),
        f"{prefix}.python.gauss": torch.tensor([python_gauss is not None, python_gauss or 0.0], dtype=torch.float64),
        f"{prefix}.python.version": torch.tensor([version], dtype=torch.int64),
    }
    for name, generator in (generators or {}).items():
        tensors[f"{prefix}.gen.{name}"] = generator.get_state()
    return tensors


def unpack_rng(
    tensors: dict[str, torch.Tensor], generators: dict[str, torch.Generator] | None = None, prefix: str = "rng"
) -> None:
    """Restore what `pack_rng` saved (the global RNGs and the named generators)."""
    torch.set_rng_state(tensors[f"{prefix}.torch"])
    pos, has_gauss = (int(v) for v in tensors[f"{prefix}.numpy.pos"])
    key = tensors[f"{prefix}.numpy.key"].numpy().astype(np.uint32)
    np.random.set_state(("MT19937", key, pos, has_gauss, float(tensors[f"{prefix}.numpy.gauss"][0])))
    has_python_gauss, python_gauss = tensors[f"{prefix}.python.gauss"].tolist()
    python_state = tuple(int(v) for v in tensors[f"{prefix}.python.state"])
    random.setstate((int(tensors[f"{prefix}.python.version"][0]), python_state, python_gauss if has_python_gauss else None))
    for name, generator in (generators or {}).items():
        generator.set_state(tensors[f"{prefix}.gen.{name}"])


def _check_resumable(run_dir: Path, config: dict[str, Any], may_change: tuple[str, ...]) -> dict[str, Any]:
    if not (run_dir / CONFIG_FILE).is_file():
        raise RunError(f"{run_dir}: nothing to resume (no {CONFIG_FILE}); start it without --resume")
    try:
        saved = json.loads((run_dir / CONFIG_FILE).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RunError(f"{run_dir / CONFIG_FILE}: not valid JSON: {exc}") from None
    changed = sorted(k for k in set(saved) | set(config) if k not in may_change and saved.get(k) != config.get(k))
    if changed:
        diff = ", ".join(f"{k} {saved.get(k)!r} -> {config.get(k)!r}" for k in changed)
        raise RunError(f"{run_dir}: --resume needs the config it was started with; changed: {diff}")
    state = _read_state(run_dir)
    if state["finished"]:
        raise RunError(f"{run_dir} already finished at step {state['step']}; nothing to resume")
    if not (run_dir / state["file"]).is_file():
        raise RunError(f"{run_dir / state['file']}: the resumable state named in {STATE_FILE} is missing")
    return state


def _read_state(run_dir: Path) -> dict[str, Any]:
    path = run_dir / STATE_FILE
    if not path.is_file():
        raise RunError(
            f"{run_dir}: no resumable state ({STATE_FILE}): it stopped before its first checkpoint; start again with --overwrite"
        )
    try:
        state = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RunError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(state, dict) or not isinstance(state.get("step"), int) or "finished" not in state:
        raise RunError(f"{path}: not a state file (needs step, file, finished)")
    return state


def _read_log(run_dir: Path) -> list[dict[str, Any]]:
    path = run_dir / LOG_FILE
    if not path.is_file():
        return []
    records = []
    for line in path.read_text().splitlines():
        with contextlib.suppress(json.JSONDecodeError):  # a SIGKILL can cut the last line short
            records.append(json.loads(line))
    return records

"""The one acting interface: a loaded policy turns env-unit states into clipped env-unit action chunks.

`Policy.act` takes states [B, state_dim] (and, for a policy that uses them, the previous states), and
for a flow per-row `seeds` or explicit `noise`; it pads the batch to a multiple of four rows
(`pusht.seeding.pad_rows`, so a row's actions never depend on its batch mates; a graph whose rows are the same
alone as in any batch runs unpadded, `batch_multiple`) and returns actions
[B, horizon, action_dim]. Backends implement `_run` once each: ONNX Runtime (`acting.onnx_backend`)
and torch (`acting.torch_backend`, imported only when asked for).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from policies.card import Card, CardError
from pusht.seeding import BATCH_MULTIPLE, pad_rows, row_noise

__all__ = ["Policy"]


class Policy:
    """A policy behind one card, run by one backend; subclasses implement `_run` (and may narrow `check_num_steps`)."""

    backend = ""
    takes_prev_state = False
    shares_zero_noise = False
    """Whether `_run` may get one read-only zero-noise array for every call (its backend never writes an input)."""
    batch_multiple = BATCH_MULTIPLE
    """`act` pads a call to a multiple of this many rows: 1 where each row's actions are the same alone as in any batch"""

    def __init__(self, card: Card) -> None:
        self.card = card
        self.name = card.path.stem
        self.kind = card.kind
        self.horizon = card.horizon
        self.state_dim = card.state_dim
        self.action_dim = card.action_dim
        self.default_num_steps = card.num_steps
        # A flow whose start noise is scaled to 0 gets zeros: drawing noise from a seed costs ~10 us per request.
        self.uses_noise = card.uses_noise
        self._rng = np.random.default_rng()
        self._zeros: dict[int, np.ndarray] = {}

    def act(
        self,
        states: np.ndarray,
        prev_states: np.ndarray | None = None,
        *,
        seeds: Sequence[int] | None = None,
        noise: np.ndarray | None = None,
        num_steps: int | None = None,
        noise_scale: float = 1.0,
    ) -> np.ndarray:
        """Actions float32 [B, horizon, action_dim] in env units, clipped, for states float32 [B, state_dim].

        Flow start noise: `noise` [B, horizon, action_dim] if given, else row i's from seeds[i] (`row_noise`), else a
        fresh draw; times `noise_scale`. mse ignores seeds and noise. `prev_states` default to `states`."""
        states = np.ascontiguousarray(states, dtype=np.float32)
        if states.ndim != 2 or states.shape[1] != self.state_dim or len(states) == 0:
            raise ValueError(f"states must have shape [B >= 1, {self.state_dim}], got {list(states.shape)}")
        rows = len(states)
        if self.kind == "flow":
            if noise is None and seeds is None and not self.uses_noise and noise_scale == 1.0 and self.shares_zero_noise:
                noise = self._zero_noise(rows + -rows % self.batch_multiple)  # already padded
            else:
                noise = self._noise(rows, seeds, noise)
                if noise_scale != 1.0:
                    noise = noise * np.float32(noise_scale)
                noise = pad_rows(noise, self.batch_multiple)
        prev = None
        if self.takes_prev_state:
            prev = states if prev_states is None else np.ascontiguousarray(prev_states, dtype=np.float32)
            if prev.shape != states.shape:
                raise ValueError(f"prev_states must have the shape of states {list(states.shape)}, got {list(prev.shape)}")
            prev = pad_rows(prev, self.batch_multiple)
        return self._run(pad_rows(states, self.batch_multiple), prev, noise, num_steps)[:rows]

    def check_num_steps(self, num_steps: int) -> str | None:
        """None if a chunk can be sampled in `num_steps` flow steps, else why not."""
        if self.kind != "flow":
            return f"num_steps applies to flow policies; policy {self.name!r} is {self.kind} (one network evaluation per chunk)"
        trained = self.card.sampler_steps
        if trained is not None and num_steps != trained:
            return (
                f"num_steps={num_steps} is not available: policy {self.name!r} was trained to sample in {trained} "
                f"step{'s' if trained != 1 else ''}, and other counts do not give its actions"
            )
        return None

    def network_evaluations(self, num_steps: int | None = None) -> int:
        """Network evaluations per chunk (`Card.network_evaluations`)."""
        return self.card.network_evaluations(num_steps or self.default_num_steps)

    def check_outputs(self) -> None:
        """One call on 8 fixed states: CardError naming the file on a wrong shape or a non-finite output (broken weights)."""
        states = self.probe_states(8)
        states[0] = 256.0
        where = self.card.onnx_path if self.backend == "onnx" else self.card.stem.with_suffix(".safetensors")
        try:
            out = np.asarray(self.act(states, seeds=range(8)))
        except Exception as exc:
            raise CardError(f"{where}: test inference failed: {exc}") from exc
        expected = (8, self.horizon, self.action_dim)
        if out.shape != expected:
            raise CardError(f"{where}: returns shape {list(out.shape)}, its card says [B, {self.horizon}, {self.action_dim}]")
        if not np.isfinite(out).all():
            raise CardError(f"{where}: test output is not finite (NaN or inf): broken weights")

    def probe_states(self, rows: int) -> np.ndarray:
        """`rows` fixed float32 states spread over the arena (the last dimension an angle), for checks at load time."""
        rng = np.random.default_rng(0)
        states = rng.uniform(0, 512, (rows, self.state_dim)).astype(np.float32)
        states[:, -1] = rng.uniform(0, 2 * np.pi, rows)
        return states

    def _zero_noise(self, rows: int) -> np.ndarray:
        """Read-only zero noise [rows, horizon, action_dim], kept for small batches (a service's usual calls)."""
        zeros = self._zeros.get(rows)
        if zeros is None:
            zeros = np.zeros((rows, self.horizon, self.action_dim), dtype=np.float32)
            zeros.flags.writeable = False
            if rows <= 64:
                self._zeros[rows] = zeros
        return zeros

    def _noise(self, rows: int, seeds: Sequence[int] | None, noise: np.ndarray | None) -> np.ndarray:
        shape = (rows, self.horizon, self.action_dim)
        if noise is not None:
            noise = np.ascontiguousarray(noise, dtype=np.float32)
            if noise.shape != shape:
                raise ValueError(f"noise must have shape {list(shape)}, got {list(noise.shape)}")
            return noise
        if seeds is not None and len(seeds) != rows:
            raise ValueError(f"seeds has {len(seeds)} entries for {rows} states; give one seed per state")
        if not self.uses_noise:
            return np.zeros(shape, dtype=np.float32)
        if seeds is not None:
            return row_noise(seeds, self.horizon, self.action_dim)
        return self._rng.standard_normal(shape, dtype=np.float32)

    def _run(
        self, states: np.ndarray, prev_states: np.ndarray | None, noise: np.ndarray | None, num_steps: int | None
    ) -> np.ndarray:
        raise NotImplementedError

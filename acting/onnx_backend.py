"""The ONNX Runtime backend: the exported graph NAME.onnx beside its card, and the one place ORT sessions are built."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from acting.policy import Policy
from policies.card import Card, CardError, require_regular_file

__all__ = ["OnnxPolicy", "batch_invariant", "onnx_session"]

INVARIANCE_SIZES = (2, 4, 5)
"""the batch sizes whose rows `batch_invariant` compares with the same rows alone"""


def onnx_session(path: str | Path, threads: int = 1):
    """An ONNX Runtime CPU session for `path`, tuned for small batches; CardError naming the file if it does not load."""
    import onnxruntime as ort

    path = Path(path)
    require_regular_file(path, "ONNX file")
    options = ort.SessionOptions()
    # One chunk is a few hundred microseconds of compute: thread pools and parallel graph execution
    # cost more in wake-ups than they save, and a server's event loop needs the other core.
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.log_severity_level = 3
    try:
        return ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # ORT raises its own unrelated types for a bad file
        raise CardError(f"{path}: not a loadable ONNX model: {exc}") from None


class OnnxPolicy(Policy):
    """A policy exported to ONNX (normalization, clipping and the flow's unrolled steps inside the graph)."""

    backend = "onnx"
    shares_zero_noise = True  # ORT reads its feeds only

    def __init__(self, card: Card, threads: int = 1) -> None:
        super().__init__(card)
        path = card.onnx_path
        self._session = onnx_session(path, threads)
        inputs = {i.name for i in self._session.get_inputs()}
        expected = {"state", "noise"} if self.kind == "flow" else {"state"}
        self.takes_prev_state = "prev_state" in inputs
        if inputs - {"prev_state"} != expected:
            raise CardError(
                f"{path}: has inputs {sorted(inputs)}, a {self.kind} policy takes {sorted(expected)} (and optionally prev_state)"
            )
        self._output = self._session.get_outputs()[0].name
        # InferenceSession.run checks its feeds in Python (~10 us cold after a model call, on every call); ours are always
        # the graph's own inputs as numpy arrays, so call the binding directly where this ORT version has it.
        inner = getattr(self._session, "_sess", None)
        self._session_run = inner.run if inner is not None else self._session.run  # (output names, feeds, run options)
        # A graph exported as batch-invariant (training.export checks it) runs unpadded once this machine agrees: padding
        # one request to four rows costs a one-pass student 2.5x its model call.
        if (card.data["onnx"] or {}).get("batch_invariant") and self._invariant_here():
            self.batch_multiple = 1

    def _invariant_here(self) -> bool:
        """`batch_invariant` on 16 fixed states (and noises) spread over the arena, in this process's ONNX Runtime."""
        states = self.probe_states(16)
        noise = None
        if self.kind == "flow":
            noise = np.random.default_rng(1).standard_normal((16, self.horizon, self.action_dim), dtype=np.float32)
        return batch_invariant(lambda s, n: self._run(s, s if self.takes_prev_state else None, n, None), states, noise)

    def check_num_steps(self, num_steps: int) -> str | None:
        """The unrolled graph has one step count; other counts need the torch backend."""
        problem = super().check_num_steps(num_steps)
        if problem is None and num_steps != self.default_num_steps:
            problem = (
                f"num_steps={num_steps} is not available on the onnx backend: {self.card.onnx_path.name} unrolls "
                f"{self.default_num_steps} flow steps (the torch backend or checkpoint runs other counts)"
            )
        return problem

    def _run(
        self, states: np.ndarray, prev_states: np.ndarray | None, noise: np.ndarray | None, num_steps: int | None
    ) -> np.ndarray:
        feeds = {"state": states}
        if noise is not None:
            feeds["noise"] = noise
        if prev_states is not None:
            feeds["prev_state"] = prev_states
        return self._session_run([self._output], feeds, None)[0]


def batch_invariant(run, states: np.ndarray, noise: np.ndarray | None, sizes: tuple[int, ...] = INVARIANCE_SIZES) -> bool:
    """Whether `run` (states [B, S], noise [B, H, A] or None -> actions) gives each row the same bits alone as inside
    consecutive batches of each of `sizes` rows."""

    def rows(size: int) -> np.ndarray:
        return np.concatenate(
            [run(states[i : i + size], None if noise is None else noise[i : i + size]) for i in range(0, len(states), size)]
        )

    alone = rows(1)
    return all(np.array_equal(rows(size), alone) for size in sizes)

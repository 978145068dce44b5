"""Export checkpoints to ONNX: env-unit `state` [B, S] (and flow `noise` [B, H, A]) in, clipped `actions` [B, H, A] out.

    python -m training.export                          # models/mse.onnx and models/flow.onnx
    python -m training.export --checkpoint runs/x/final --out /tmp/x.onnx

The shapes are the checkpoint's own (its card's state_dim S, horizon H, action_dim A: 5, 12, 2 for
every shipped policy). Normalization, the policy (flow: its Euler steps unrolled), denormalization
and clipping are all in the graph. Each export is checked with onnx.checker and against the torch
ActingPolicy in ONNX Runtime (`acting.onnx_backend.onnx_session`, the session every ONNX user gets),
then recorded in the checkpoint's card (`onnx`) when it is written beside the card.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from acting import read_card
from acting.onnx_backend import batch_invariant, onnx_session
from policies.base import ActingPolicy
from policies.checkpoint import CheckpointError, checkpoint_stem, load_acting_policy, update_card
from pusht.spec import DEFAULT_NUM_STEPS
from training.cli import HelpFormatter

OPSET = 18
# Exported and torch actions must agree to this many pixels on random states (float32 rounding only).
VERIFY_ATOL = 1e-3
INVARIANCE_CHECK_SIZES = (2, 3, 4, 5, 8, 37)
"""batch sizes whose rows `rows_batch_invariant` compares with the same rows alone"""


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: export one checkpoint or every named one in a models folder."""
    parser = _parser()
    args = parser.parse_args(argv)

    if args.checkpoint is not None:
        jobs = [
            (
                checkpoint_stem(args.checkpoint),
                Path(args.out) if args.out else checkpoint_stem(args.checkpoint).with_suffix(".onnx"),
            )
        ]
    else:
        if args.out is not None:
            parser.error("--out needs --checkpoint")
        jobs = [(Path(args.models_dir) / name, Path(args.models_dir) / f"{name}.onnx") for name in args.names]
    if args.triton_repo is not None:
        if args.out is not None:
            parser.error("--out and --triton-repo exclude each other")
        jobs = [(stem, Path(args.triton_repo) / stem.name / "1" / "model.onnx") for stem, _ in jobs]
    status = 0
    for stem, out in jobs:
        try:
            info = export_onnx(stem, out, num_steps=args.num_steps, opset=args.opset)
            if args.triton_repo is not None:
                from training.triton_repo import write_config

                print(
                    f"{write_config(out.parent.parent, read_card(stem))}: Triton config (onnxruntime backend, dynamic batching)"
                )
        except (CheckpointError, ValueError, OSError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            status = 2
            continue
        note = "card updated" if info["card_updated"] else "not beside the card: card left unchanged"
        print(
            f"{stem} -> {out} (inputs {info['inputs']}, outputs {info['outputs']}, opset {info['opset']}, max diff {info['max_abs_diff']:.2e} px; {note})"
        )
    return status


def _parser() -> argparse.ArgumentParser:
    """The command line."""
    parser = argparse.ArgumentParser(
        prog="python -m training.export",
        description="Export checkpoints (NAME.safetensors + NAME.json) to ONNX files with normalization and clipping inside the graph.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument(
        "--models-dir", default="models", help="folder of the checkpoints; writes MODELS_DIR/NAME.onnx for each --names"
    )
    parser.add_argument("--names", nargs="+", default=["mse", "flow"], help="checkpoint names inside --models-dir")
    parser.add_argument("--checkpoint", default=None, help="export this one checkpoint stem (DIR/NAME) instead; needs --out")
    parser.add_argument(
        "--out",
        default=None,
        help="output .onnx path for --checkpoint (default: STEM.onnx; the card records it only if beside the card)",
    )
    parser.add_argument(
        "--num-steps",
        type=int,
        default=None,
        help=f"flow: Euler steps unrolled into the graph (default: a flow's trained count (sampler_steps), else {DEFAULT_NUM_STEPS})",
    )
    parser.add_argument(
        "--triton-repo",
        default=None,
        help="write each export as a Triton model repository entry DIR/NAME/1/model.onnx with its config.pbtxt instead",
    )
    parser.add_argument("--opset", type=int, default=OPSET, help="ONNX opset (>= 17)")
    return parser


def default_num_steps(stem: str | Path) -> int:
    """The Euler steps to unroll for a checkpoint: a flow's trained count (`sampler_steps`), else DEFAULT_NUM_STEPS."""
    return int(read_card(checkpoint_stem(stem)).sampler_steps or DEFAULT_NUM_STEPS)


def export_onnx(
    stem: str | Path, out_path: str | Path | None = None, num_steps: int | None = None, opset: int = OPSET
) -> dict[str, Any]:
    """Export checkpoint `stem` to `out_path` (default STEM.onnx) and verify it; returns the onnx info (plus max_abs_diff).

    `num_steps=None` unrolls the checkpoint's own count (`default_num_steps`). The card also records whether each row's
    actions are the same alone as in a batch (`batch_invariant`).

    The card records the export only when the file lies beside it, where the service looks for it;
    an export elsewhere leaves the card as it was.
    """
    if opset < 17:
        raise ValueError(f"opset must be >= 17, got {opset}")
    stem = checkpoint_stem(stem)
    if num_steps is None:
        num_steps = default_num_steps(stem)
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    out = Path(out_path) if out_path is not None else stem.with_suffix(".onnx")
    if out.suffix != ".onnx":
        raise ValueError(f"{out}: the output file must end in .onnx")
    acting = load_acting_policy(stem, num_steps=num_steps).eval()
    inputs = graph_inputs(acting)
    graph = _GraphModule(acting, inputs).eval()
    example = _example_inputs(acting, batch=4, seed=0)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp.onnx")
    try:
        try:
            _torch_export(graph, example, inputs, tmp, opset)
        except Exception as exc:  # torch.export / onnxscript raise their own error types
            raise ValueError(f"{stem}: ONNX export failed: {type(exc).__name__}: {exc}") from exc
        max_diff = verify_onnx(tmp, acting)
        invariant = rows_batch_invariant(tmp, acting)
        opset = _model_opset(tmp)  # the exporter may raise a requested opset; record what the file has
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)
    info = {
        "file": out.name,
        "inputs": inputs,
        "outputs": ["actions"],
        "num_steps": num_steps,  # meaningful for flow only; recorded for both so every card reads the same
        "opset": opset,
        "batch_invariant": invariant,
    }
    beside_card = out.resolve().parent == stem.resolve().parent
    if beside_card:
        update_card(stem, onnx=info)
    return dict(info, max_abs_diff=max_diff, card_updated=beside_card)


def verify_onnx(path: str | Path, acting: ActingPolicy, batches: tuple[int, ...] = (1, 37)) -> float:
    """Check the ONNX file (onnx.checker, names, dtypes) and its agreement with `acting` in ONNX Runtime; returns the max |diff| in px."""
    import onnx

    path = Path(path)
    model = onnx.load(str(path))
    try:
        onnx.checker.check_model(model, full_check=True)
    except onnx.checker.ValidationError as exc:
        raise ValueError(f"{path}: invalid ONNX model: {exc}") from None
    session = onnx_session(path)
    expected_inputs = graph_inputs(acting)
    names = [i.name for i in session.get_inputs()]
    if names != expected_inputs or [o.name for o in session.get_outputs()] != ["actions"]:
        raise ValueError(
            f"{path}: inputs {names} / outputs {[o.name for o in session.get_outputs()]}, expected {expected_inputs} / ['actions']"
        )
    worst = 0.0
    for i, batch in enumerate(batches):
        example = _example_inputs(acting, batch=batch, seed=1000 + i)
        with torch.inference_mode():
            want = _GraphModule(acting, expected_inputs)(*example).numpy()
        got = session.run(["actions"], {name: t.numpy() for name, t in zip(expected_inputs, example)})[0]
        if got.dtype != np.float32 or got.shape != want.shape:
            raise ValueError(f"{path}: output {got.dtype} {list(got.shape)}, expected float32 {list(want.shape)}")
        worst = max(worst, float(np.abs(got - want).max()))
    if worst > VERIFY_ATOL:
        raise ValueError(f"{path}: ONNX Runtime and torch differ by {worst:.3g} px (> {VERIFY_ATOL})")
    return worst


def rows_batch_invariant(path: str | Path, acting: ActingPolicy, rows: int = 512) -> bool:
    """Whether the ONNX file gives each of `rows` example states (and noises) the same bits alone as inside batches of
    `INVARIANCE_CHECK_SIZES` rows: then the acting layer may run it unpadded (`acting.Policy.batch_multiple`)."""
    session = onnx_session(path)
    inputs = graph_inputs(acting)
    example = dict(zip(inputs, (t.numpy() for t in _example_inputs(acting, batch=rows, seed=7))))

    def run(states: np.ndarray, noise: np.ndarray | None) -> np.ndarray:
        feeds = {"state": states, "noise": noise, "prev_state": states}
        return session.run(["actions"], {name: feeds[name] for name in inputs})[0]

    return batch_invariant(run, example["state"], example.get("noise"), INVARIANCE_CHECK_SIZES)


def _model_opset(path: Path) -> int:
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    return next(o.version for o in model.opset_import if o.domain in ("", "ai.onnx"))


def graph_inputs(acting: ActingPolicy) -> list[str]:
    """The graph's input names in order: `state`, flow's `noise`, and `prev_state` for a policy with history."""
    names = ["state", "noise"] if acting.kind == "flow" else ["state"]
    return names + ["prev_state"] if acting.policy.prev_state else names


class _GraphModule(torch.nn.Module):
    """The exported signature: forward(*inputs) in the order `graph_inputs` names them."""

    def __init__(self, acting: ActingPolicy, inputs: list[str]) -> None:
        super().__init__()
        self.acting = acting
        self.inputs = inputs

    def forward(self, *args: torch.Tensor) -> torch.Tensor:
        named = dict(zip(self.inputs, args))
        return self.acting(named["state"], named.get("noise"), prev_state=named.get("prev_state"))


def _example_inputs(acting: ActingPolicy, batch: int, seed: int) -> tuple[torch.Tensor, ...]:
    """Env-unit states spread over the arena (the last dimension an angle in [0, 2π)), for flow standard-normal noise,
    and for a policy with history the states a step before (up to 10 px and 0.1 rad away), in the checkpoint's own shapes."""
    policy = acting.policy
    gen = torch.Generator().manual_seed(seed)
    scale = torch.tensor([512.0] * (policy.state_dim - 1) + [2 * np.pi])
    state = torch.rand(batch, policy.state_dim, generator=gen) * scale
    out = [state]
    if acting.kind == "flow":
        out.append(torch.randn(batch, policy.horizon, policy.action_dim, generator=gen))
    if policy.prev_state:
        step = torch.tensor([10.0] * (policy.state_dim - 1) + [0.1])
        out.append(state + (2 * torch.rand(batch, policy.state_dim, generator=gen) - 1) * step)
    return tuple(out)


def _torch_export(graph: torch.nn.Module, example: tuple[torch.Tensor, ...], inputs: list[str], path: Path, opset: int) -> None:
    """torch.onnx.export with the dynamo exporter, a dynamic batch dimension and the weights inside the one file."""
    batch = torch.export.Dim("batch", min=1, max=1 << 20)
    dynamic = {"args": tuple({0: batch} for _ in inputs)}  # `_GraphModule.forward(*args)`
    # The exporter logs and warns a lot (missing torchvision, deprecations): keep stderr for real errors.
    loggers = [logging.getLogger(n) for n in ("torch.onnx", "torch.export", "torch._dynamo", "onnxscript")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            torch.onnx.export(
                graph,
                example,
                str(path),
                input_names=inputs,
                output_names=["actions"],
                dynamic_shapes=dynamic,
                opset_version=opset,
                dynamo=True,
                external_data=False,
                optimize=True,
                verbose=False,
            )
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


if __name__ == "__main__":
    sys.exit(main())

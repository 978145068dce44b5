"""Request and response models of the API; the request model also validates `POST /act` bodies.

Validation is strict: numbers must be JSON numbers (no strings or booleans), state values finite
and within +-STATE_LIMIT, `seed`, `seeds` and `num_steps` integers; `seeds` gives one seed per row
of `states` (same length), as an alternative to one `seed` for the whole batch. NaN / Infinity tokens and overflowing
literals such as 1e999 parse to non-finite floats and are rejected.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Annotated, Any

from annotated_types import Len
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictFloat,
    StrictInt,
    create_model,
    model_validator,
)

from pusht.spec import STATE_DIM
from service.settings import MAX_NUM_STEPS, STATE_LIMIT

__all__ = ["ActRequestBase", "ActResponse", "PolicyInfo", "PoliciesResponse", "act_request_model"]

MAX_SEED = 2**63 - 1

StateValue = Annotated[StrictFloat, Field(ge=-STATE_LIMIT, le=STATE_LIMIT, allow_inf_nan=False)]
State = Annotated[
    list[StateValue],
    Len(STATE_DIM, STATE_DIM),
    Field(description="[agent_x, agent_y, block_x, block_y, block_angle] in env units (pixels, radians)"),
]
Seed = Annotated[StrictInt, Field(ge=0, le=MAX_SEED)]


class ActRequestBase(BaseModel):
    """Fields shared by every `POST /act` body; `states` is added with the configured batch limit."""

    model_config = ConfigDict(
        extra="forbid",
        allow_inf_nan=False,
        json_schema_extra={
            "examples": [
                {"policy": "flow", "state": [222.0, 97.0, 222.0, 222.0, 0.8], "seed": 0},
                {"policy": "mse", "states": [[222.0, 97.0, 222.0, 222.0, 0.8], [300.0, 400.0, 250.0, 260.0, 3.1]]},
                {
                    "policy": "flow",
                    "states": [[222.0, 97.0, 222.0, 222.0, 0.8], [300.0, 400.0, 250.0, 260.0, 3.1]],
                    "seeds": [7, 8],
                },
            ]
        },
    )

    policy: str | None = Field(
        None, min_length=1, max_length=200, description="name of a loaded policy (see GET /policies); omitted: the default policy"
    )
    state: State | None = Field(
        None, description="one state; the answer is one chunk [horizon, action_dim] (the policy's, see GET /policies)"
    )
    seed: StrictInt | None = Field(
        None,
        ge=0,
        le=MAX_SEED,
        description=(
            "noise seed for the whole request, for a stochastic policy (GET /policies): the same seed and states give the "
            "same actions; omitted (and no `seeds`): fresh noise. A policy that is not stochastic ignores it"
        ),
    )
    num_steps: StrictInt | None = Field(
        None,
        ge=1,
        le=MAX_NUM_STEPS,
        description=(
            "flow Euler steps (default: the exported count; the onnx backend runs only that count, a distilled flow only "
            "its own); a 422 for mse, which has none"
        ),
    )

    @model_validator(mode="after")
    def _exactly_one_input(self) -> "ActRequestBase":
        has_state = self.state is not None
        has_states = getattr(self, "states", None) is not None
        if has_state == has_states:
            raise ValueError(f"give exactly one of 'state' (one state of {STATE_DIM} numbers) or 'states' (a list of them)")
        seeds = getattr(self, "seeds", None)
        if seeds is not None:
            if has_state:
                raise ValueError("'seeds' goes with 'states' (one seed per state); with a single 'state' send 'seed'")
            if self.seed is not None:
                raise ValueError("give at most one of 'seed' (one for the whole batch) or 'seeds' (one per state)")
            if len(seeds) != len(self.states):  # type: ignore[attr-defined]
                raise ValueError(
                    f"'seeds' has {len(seeds)} entries but 'states' has {len(self.states)}: give one seed per state"  # type: ignore[attr-defined]
                )
        return self


@lru_cache
def act_request_model(max_states: int) -> type[ActRequestBase]:
    """The `POST /act` body model with `states` limited to `max_states` entries."""
    states_type = Annotated[
        list[State],
        Field(
            min_length=1,
            max_length=max_states,
            description=f"a batch of 1..{max_states} states; the answer is [B, horizon, action_dim]",
        ),
    ]
    seeds_type = Annotated[
        list[Seed],
        Field(
            min_length=1,
            max_length=max_states,
            description=(
                "one noise seed per state of `states`: row i's actions equal those of a single request with "
                "`state` = states[i] and `seed` = seeds[i], whatever else is in the batch (ignored by a policy that is not stochastic)"
            ),
        ),
    ]
    return create_model(
        "ActRequest",
        __base__=ActRequestBase,
        __doc__="Body of `POST /act`: a policy name, exactly one of `state` or `states`, and `seed` or `seeds`.",
        states=(states_type | None, None),
        seeds=(seeds_type | None, None),
    )


class ActResponse(BaseModel):
    """Actions in env units, clipped to [0, 512]: [horizon, action_dim] for `state`, [B, horizon, action_dim] for `states`.

    horizon and action_dim are the policy's, from its card (GET /policies lists them)."""

    policy: str
    kind: str = Field(description="mse or flow")
    backend: str = Field(description="onnx or torch")
    actions: list[list[float]] | list[list[list[float]]]


class PolicyInfo(BaseModel):
    """One loaded policy, from its card."""

    name: str
    kind: str = Field(
        description="what it computes: mse; flow (a flow-matching sampler); flow-chooser (a flow's candidate chunks, "
        "the one a learned outcome model prefers plays)"
    )
    stochastic: bool = Field(
        description="whether its actions depend on the request's seed (its noise); false: a seed changes nothing"
    )
    default: bool = Field(description="whether requests without a policy name get it (exactly one policy is the default)")
    num_parameters: int | None = None
    horizon: int = Field(description="actions per chunk: every answer of this policy is [horizon, action_dim] per state")
    action_dim: int = Field(description="numbers per action (the agent's target x, y)")
    num_steps: int | None = Field(None, description="flow Euler steps of the exported graph")
    network_evaluations: int = Field(
        description="network passes per chunk at the default settings: flow's Euler steps (times its candidates, plus their outcome-model passes, for a flow with an outcome chooser), mse's 1"
    )
    steps: int | None = Field(None, description="training steps")
    evaluation: Any = Field(None, description="the card's evaluation results during training, with their seeds")
    heldout_evaluation: Any = Field(None, description="the card's scores on held-out episode seeds, when shipped")
    git_commit: str | None = None


class PoliciesResponse(BaseModel):
    """The loaded policies and the backend that runs them."""

    backend: str
    policies: list[PolicyInfo]


class ErrorResponse(BaseModel):
    """Every error: `detail` is a message, or a list of {loc, msg, type} for validation errors."""

    detail: str | list[dict[str, Any]]

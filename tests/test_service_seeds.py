"""Per-row seeds in `POST /act`: row i answers as a single request with seeds[i], whatever its batch mates.

Against a real uvicorn on loopback (random test models, then the shipped models/), plus the batcher
in process for requests split over several model calls.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import httpx
import numpy as np
import pytest

from pusht.rollout import chunk_noise, row_noise
from service.settings import Settings
from tests.service_fixtures import UvicornProcess, iter_lines, raw_burst

rng = np.random.default_rng(3)
STATES = np.column_stack([rng.uniform(20, 490, (6, 4)), rng.uniform(0, 6.28, 6)]).round(3).tolist()
SEEDS = [10**18 + 7, 0, 2**63 - 1, 5, 5, 123]


def act(url: str, **body) -> httpx.Response:
    return httpx.post(f"{url}/act", json=body, timeout=30)


@pytest.mark.slow
def test_row_i_equals_a_single_request_with_seeds_i(server: UvicornProcess) -> None:
    from acting import load_policy

    batch = act(server.url, policy="flow", states=STATES, seeds=SEEDS)
    assert batch.status_code == 200, batch.text
    actions = np.asarray(batch.json()["actions"], dtype=np.float32)
    assert actions.shape == (6, 12, 2)
    # model calls are padded to a multiple of 4 rows, so the rows are equal to the last bit
    for i, (state, seed) in enumerate(zip(STATES, SEEDS, strict=True)):
        alone = act(server.url, policy="flow", state=state, seed=seed).json()["actions"]
        np.testing.assert_array_equal(actions[i], np.asarray(alone, dtype=np.float32))
    # other batch mates, other order: the same rows
    order = [5, 3, 0, 4, 1, 2]
    shuffled = act(server.url, policy="flow", states=[STATES[i] for i in order], seeds=[SEEDS[i] for i in order]).json()
    np.testing.assert_array_equal(np.asarray(shuffled["actions"], dtype=np.float32), actions[order])
    # equal seeds on equal states give equal rows; the noise is row_noise(seeds), as in process
    twice = np.asarray(act(server.url, policy="flow", states=[STATES[0]] * 2, seeds=[9, 9]).json()["actions"])
    np.testing.assert_array_equal(twice[0], twice[1])
    policy = load_policy(server.models_dir / "flow.json", backend="onnx")
    expected = policy.act(np.asarray(STATES, np.float32), noise=row_noise(SEEDS, 12, 2))
    np.testing.assert_allclose(actions, expected, atol=1e-4, rtol=0)
    # a whole-batch seed keeps its meaning: chunk_noise(seed, B), not per-row noise
    whole = np.asarray(act(server.url, policy="flow", states=STATES, seed=5).json()["actions"])
    np.testing.assert_allclose(whole, policy.act(np.asarray(STATES, np.float32), noise=chunk_noise(5, 6)), atol=1e-4, rtol=0)
    # mse ignores seeds, as it ignores seed
    mse = [act(server.url, policy="mse", states=STATES, **extra).json()["actions"] for extra in ({"seeds": SEEDS}, {})]
    assert mse[0] == mse[1]


@pytest.mark.slow
def test_requests_with_seeds_still_merge_into_shared_model_calls(server: UvicornProcess) -> None:
    def calls_and_requests() -> tuple[float, float]:
        values = {}
        for line in iter_lines(httpx.get(f"{server.url}/metrics").text):
            for key in ("pusht_batch_requests_count", "pusht_batch_requests_sum"):
                if line.startswith(key + '{policy="flow"}'):
                    values[key] = float(line.split()[-1])
        return values.get("pusht_batch_requests_count", 0.0), values.get("pusht_batch_requests_sum", 0.0)

    n = 64
    # two rows a request, unless two such requests overflow one call's cost budget (the shipped flow's 16 candidates)
    unit = next(p for p in httpx.get(f"{server.url}/policies").json()["policies"] if p["name"] == "flow")["network_evaluations"]
    rows = 2 if 2 * 2 * unit <= Settings().batch_max_cost else 1
    bodies = [
        {
            "policy": "flow",
            "states": [STATES[(i + r) % 6] for r in range(rows)],
            "seeds": [1000 * (r + 1) + i for r in range(rows)],
        }
        for i in range(n)
    ]
    alone = [act(server.url, **body).json()["actions"] for body in bodies]
    calls0, reqs0 = calls_and_requests()
    together = asyncio.run(raw_burst(server.port, [json.dumps(b).encode() for b in bodies], connections=32))
    calls1, reqs1 = calls_and_requests()
    assert [status for status, _ in together] == [200] * n
    np.testing.assert_allclose([json.loads(body)["actions"] for _, body in together], alone, atol=1e-4, rtol=0)
    assert reqs1 - reqs0 == n and calls1 - calls0 < n, f"{n} requests took {calls1 - calls0} model calls: no merging"


BAD_SEEDS = [
    ("lengths differ", {"states": STATES[:3], "seeds": [1, 2]}, "'seeds' has 2 entries but 'states' has 3"),
    ("more seeds than states", {"states": STATES[:1], "seeds": [1, 2]}, "'seeds' has 2 entries but 'states' has 1"),
    ("seeds with state", {"state": STATES[0], "seeds": [1]}, "'seeds' goes with 'states'"),
    ("seeds with seed", {"states": STATES[:2], "seeds": [1, 2], "seed": 3}, "at most one of 'seed'"),
    ("negative", {"states": STATES[:2], "seeds": [1, -1]}, "greater than or equal to 0"),
    ("2**63", {"states": STATES[:2], "seeds": [1, 2**63]}, "less than or equal to"),
    ("float", {"states": STATES[:2], "seeds": [1, 2.0]}, "valid integer"),
    ("string", {"states": STATES[:2], "seeds": [1, "2"]}, "valid integer"),
    ("bool", {"states": STATES[:2], "seeds": [1, True]}, "valid integer"),
    ("null entry", {"states": STATES[:2], "seeds": [1, None]}, "valid integer"),
    ("empty", {"states": STATES[:2], "seeds": []}, "at least 1"),
    ("not a list", {"states": STATES[:2], "seeds": 7}, "valid array"),
    ("too many", {"states": [STATES[0]] * 65, "seeds": list(range(65))}, "at most 64"),
]


@pytest.mark.slow
@pytest.mark.parametrize("case, body, message", BAD_SEEDS, ids=[c[0] for c in BAD_SEEDS])
def test_bad_seeds_get_a_422_that_says_why(case: str, body: dict, message: str, server: UvicornProcess) -> None:
    response = act(server.url, policy="flow", **body)
    assert response.status_code == 422, response.text
    assert message in json.dumps(response.json()["detail"]), response.text


def test_a_request_split_over_model_calls_keeps_its_noise(test_models: Path) -> None:
    """Rows of one request spread over several calls (small cost budget) get the noise of one unsplit call."""
    from acting import load_policy
    from service.batching import Batcher

    policy = load_policy(test_models / "flow.json", backend="onnx")
    policy.batch_multiple = 4  # calls padded to groups of four rows, as float32 graphs whose rows depend on their batch are
    states = np.asarray([STATES[i % 6] for i in range(10)], dtype=np.float32)
    seeds = list(range(50, 60))
    calls: list[int] = []

    async def run() -> list[np.ndarray]:
        # 3 flow rows' budget, below the padded group of 4 rows a call may always take: 4 rows a call
        batcher = Batcher(policy, max_cost=30, observe=lambda name, rows, reqs: calls.append(rows))
        try:
            return await asyncio.gather(
                batcher.submit(states, seed=5), batcher.submit(states, seeds=seeds), batcher.submit(states)
            )
        finally:
            batcher.close()

    whole, per_row, fresh = asyncio.run(run())
    assert max(calls) == 4 and sum(calls) == 30
    np.testing.assert_allclose(whole, policy.act(states, noise=chunk_noise(5, 10)), atol=1e-4, rtol=0)
    np.testing.assert_allclose(per_row, policy.act(states, noise=row_noise(seeds)), atol=1e-4, rtol=0)
    assert fresh.shape == (10, 12, 2) and np.isfinite(fresh).all()

"""The batched lockstep rollout runner, on the real Push-T env."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pusht.rollout import (
    BATCH_MULTIPLE,
    RolloutSummary,
    chunk_noise,
    decision_seed,
    episode_seeds,
    pad_rows,
    row_noise,
    run_episodes,
)


def _gym_pusht_env():
    import gym_pusht  # noqa: F401
    import gymnasium

    return gymnasium.make("gym_pusht/PushT-v0", obs_type="state", render_mode="rgb_array").unwrapped


def _our_env():
    from pusht.rollout import default_env_factory

    return default_env_factory()


def _have_our_env() -> bool:
    try:
        _our_env()
    except (ImportError, AttributeError):
        return False
    return True


ENV_FACTORIES = [
    pytest.param(_gym_pusht_env, id="gym-pusht"),
    pytest.param(_our_env, id="pusht", marks=pytest.mark.skipif(not _have_our_env(), reason="pusht.PushTEnv not written yet")),
]


def chase_block(states: np.ndarray, seeds: list[int]) -> np.ndarray:
    """A scripted policy that depends on the state only: aim at the block, offset by the agent's position."""
    target = 0.7 * states[:, 2:4] + 0.3 * states[:, 0:2]
    ramp = np.linspace(0.0, 1.0, 12, dtype=np.float32)[None, :, None]
    return states[:, None, 0:2] + ramp * (target - states[:, 0:2])[:, None, :]


class Recorder:
    """Wraps an act function and records each call's batch and row seeds."""

    def __init__(self, act):
        self.act = act
        self.batch_sizes: list[int] = []
        self.request_seeds: list[int] = []
        self.states: list[np.ndarray] = []

    def __call__(self, states, seeds):
        assert states.dtype == np.float32 and states.ndim == 2 and states.shape[1] == 5
        assert len(seeds) == len(states) and all(isinstance(s, int) for s in seeds)
        self.batch_sizes.append(len(states))
        self.request_seeds.append(list(seeds))
        self.states.append(states.copy())
        return self.act(states, seeds)


@pytest.mark.parametrize("factory", ENV_FACTORIES)
def test_lockstep_spreads_seeds_over_fewer_envs_with_one_call_per_decision(factory):
    seeds = episode_seeds(100000, 5)
    act = Recorder(chase_block)
    summary = run_episodes(act, seeds, num_envs=2, max_steps=30, action_horizon=12, env_factory=factory)

    # 30 steps = chunks of 12, 12, 6: three decisions an episode; pairs (0,1), (2,3), then 4 alone.
    assert act.batch_sizes == [2, 2, 2, 2, 2, 2, 1, 1, 1]
    assert summary.decisions == 9
    # each row asks with its own episode's seed and that episode's own decision index
    groups = [seeds[0:2]] * 3 + [seeds[2:4]] * 3 + [seeds[4:5]] * 3
    assert act.request_seeds == [[decision_seed(e, d % 3) for e in group] for d, group in enumerate(groups)]
    assert summary.seeds == seeds
    assert [e.length for e in summary.episodes] == [30] * 5
    assert summary.num_envs == 2
    for e in summary.episodes:
        assert 0.0 <= e.max_reward <= 1.0 and 0.0 <= e.final_coverage <= 1.0
    assert summary.mean_max_reward == pytest.approx(np.mean([e.max_reward for e in summary.episodes]))
    lo, hi = summary.mean_max_reward_ci95
    assert lo <= summary.mean_max_reward <= hi


@pytest.mark.parametrize("factory", ENV_FACTORIES)
def test_batched_rows_match_single_env_runs(factory):
    """Each row of a batch must drive its own env: batched results equal one-env-at-a-time results."""
    seeds = episode_seeds(100010, 3)
    batched = run_episodes(chase_block, seeds, num_envs=3, max_steps=40, env_factory=factory)
    single = run_episodes(chase_block, seeds, num_envs=1, max_steps=40, env_factory=factory)
    assert batched.decisions == 4 and single.decisions == 12
    # equal up to float rounding (numpy's SIMD paths may round a batch of 3 and of 1 differently)
    for b, s in zip(batched.episodes, single.episodes, strict=True):
        assert (b.seed, b.length, b.success) == (s.seed, s.length, s.success)
        assert b.max_reward == pytest.approx(s.max_reward, abs=1e-6)
        assert b.final_coverage == pytest.approx(s.final_coverage, abs=1e-6)
    # the starts differ per seed, so a row mix-up could not go unnoticed
    assert len({e.max_reward for e in batched.episodes}) == 3


def noisy_act(states, seeds):
    """chase_block plus 20 px of each row's own noise: a stand-in for flow that is cheap and seed-driven."""
    return chase_block(states, seeds) + 20.0 * row_noise(seeds)


def test_summary_is_deterministic():
    """Also the default env factory: our pusht.PushTEnv."""
    seeds = episode_seeds(100020, 4)
    first = run_episodes(noisy_act, seeds, num_envs=3, max_steps=36).to_dict()
    second = run_episodes(noisy_act, seeds, num_envs=3, max_steps=36).to_dict()
    for d in (first, second):
        d.pop("wall_time_s")
    assert first == second
    other = run_episodes(noisy_act, episode_seeds(100021, 3), num_envs=3, max_steps=36)
    # episode 100021 is the same episode whichever run plays it, with whatever neighbours
    assert other.episodes == [e for e in run_episodes(noisy_act, seeds, num_envs=3, max_steps=36).episodes[1:]]


@pytest.mark.parametrize("num_envs", [1, 2, 5])
def test_an_episode_depends_on_its_own_seed_only(num_envs):
    seeds = episode_seeds(100030, 5)
    alone = [run_episodes(noisy_act, [s], num_envs=1, max_steps=48, record_trajectories=True) for s in seeds]
    together = run_episodes(noisy_act, seeds, num_envs=num_envs, max_steps=48, record_trajectories=True)
    assert together.episodes == [a.episodes[0] for a in alone]
    for t, a in zip(together.trajectories, alone, strict=True):
        np.testing.assert_array_equal(t.actions, a.trajectories[0].actions)  # the same noise, row for row


class _StartsAtGoal:
    """Our env, restored with the block exactly on its goal pose so that step 1 succeeds."""

    def __init__(self):
        self.env = _our_env()

    def reset(self, seed=None):
        return self.env.reset(seed=seed, options={"restore_state": [100.0, 100.0, 256.0, 256.0, math.pi / 4]})

    def step(self, action):
        return self.env.step(action)

    def close(self):
        self.env.close()


def test_success_terminates_the_episode_and_counts():
    hold = lambda states, s: np.repeat(states[:, None, 0:2], 12, axis=1)  # noqa: E731
    summary = run_episodes(hold, [1, 2], num_envs=2, env_factory=_StartsAtGoal)
    assert [e.length for e in summary.episodes] == [1, 1]
    assert all(e.success and e.max_reward == 1.0 and e.final_coverage > 0.95 for e in summary.episodes)
    assert summary.success_rate == 1.0 and summary.decisions == 1


def test_record_frames_of_the_first_episode():
    captions = []

    def keep(frame, step, coverage, success):
        captions.append((step, coverage, success))
        return frame[::10, ::10]

    summary = run_episodes(
        chase_block,
        [100000, 100001],
        num_envs=2,
        max_steps=13,
        env_factory=_gym_pusht_env,
        record_frames=keep,
    )
    assert len(summary.frames) == 14  # the reset frame and one per step
    assert summary.frames[0].shape == (68, 68, 3)
    assert [step for step, _, _ in captions] == list(range(14))
    assert all(0.0 <= c <= 1.0 and s is False for _, c, s in captions)
    assert "frames" not in summary.to_dict()


def test_recorded_trajectories_replay_to_the_same_states():
    """Each recorded state is the observation the recorded action was executed from, episode by episode."""
    seeds = [100000, 100001, 100002]
    summary = run_episodes(chase_block, seeds, num_envs=2, max_steps=30, env_factory=_our_env, record_trajectories=True)
    assert [t.seed for t in summary.trajectories] == seeds
    for trajectory, episode in zip(summary.trajectories, summary.episodes, strict=True):
        assert trajectory.states.shape == (episode.length, 5) and trajectory.actions.shape == (episode.length, 2)
        env = _our_env()
        obs, _ = env.reset(seed=trajectory.seed)
        for state, action in zip(trajectory.states, trajectory.actions):
            np.testing.assert_array_equal(state, np.asarray(obs, dtype=np.float32))
            obs, *_ = env.step(action)
    assert run_episodes(chase_block, seeds, num_envs=2, max_steps=30, env_factory=_our_env).trajectories == []


def test_progress_callback_counts_episodes():
    calls = []
    run_episodes(
        chase_block,
        [1, 2, 3],
        num_envs=2,
        max_steps=12,
        env_factory=_gym_pusht_env,
        progress=lambda done, total: calls.append((done, total)),
    )
    assert calls == [(1, 3), (2, 3), (3, 3)]


@pytest.mark.parametrize(
    "bad_act, message",
    [
        (lambda s, r: np.zeros((len(s), 12)), "shape"),
        (lambda s, r: np.zeros((len(s) + 1, 12, 2)), "shape"),
        (lambda s, r: np.zeros((len(s), 12, 3)), "shape"),
        (lambda s, r: np.zeros((len(s), 0, 2)), "shape"),
        (lambda s, r: np.zeros((len(s), 8, 2)), "at least 12"),
        (lambda s, r: np.full((len(s), 12, 2), np.nan), "non-finite"),
        (lambda s, r: [["a"]], "numeric"),
    ],
)
def test_bad_act_output_is_a_clear_error(bad_act, message):
    with pytest.raises(ValueError, match=message):
        run_episodes(bad_act, [1, 2], num_envs=2, max_steps=12, action_horizon=12, env_factory=_gym_pusht_env)


def test_the_chunk_length_comes_from_the_actions():
    """No action_horizon: each chunk runs whole, as long as the policy makes it (16 here); shorter chunks later fail."""

    def chase16(states, seeds):
        ramp = np.linspace(0.0, 1.0, 16, dtype=np.float32)[None, :, None]
        return states[:, None, 0:2] + ramp * (states[:, 2:4] - states[:, 0:2])[:, None, :]

    act = Recorder(chase16)
    summary = run_episodes(act, [100000, 100001], num_envs=2, max_steps=40, env_factory=_our_env)
    assert summary.action_horizon == 16 and summary.to_dict()["action_horizon"] == 16
    assert summary.decisions == 3 and act.batch_sizes == [2, 2, 2]  # 40 steps = chunks of 16, 16, 8
    assert [e.length for e in summary.episodes] == [40, 40]
    assert run_episodes(chase16, [100000], num_envs=1, max_steps=40, action_horizon=5, env_factory=_our_env).decisions == 8
    calls = []

    def shrinking(states, seeds):
        calls.append(len(states))
        return chase16(states, seeds)[:, : 16 if len(calls) == 1 else 12]

    with pytest.raises(ValueError, match="at least 16"):
        run_episodes(shrinking, [100000], num_envs=1, max_steps=40, env_factory=_our_env)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"seeds": []}, "empty"),
        ({"seeds": [1, -2]}, "episode seed"),
        ({"seeds": [1.5]}, "episode seed"),
        ({"num_envs": 0}, "num_envs"),
        ({"max_steps": 0}, "max_steps"),
        ({"action_horizon": -1}, "action_horizon"),
        ({"progress": "yes"}, "progress"),
    ],
)
def test_bad_arguments_are_clear_errors(kwargs, message):
    args = {"seeds": [1], "num_envs": 1, "env_factory": _gym_pusht_env, **kwargs}
    with pytest.raises(ValueError, match=message):
        run_episodes(chase_block, **args)


def test_episode_seeds():
    assert episode_seeds(200000, 3) == [200000, 200001, 200002]
    with pytest.raises(ValueError, match="positive"):
        episode_seeds(0, 0)


def test_decision_seed_is_deterministic_distinct_and_in_range():
    values = [decision_seed(s, d) for s in (0, 1, 100000, 2**62) for d in range(200)]
    assert all(0 <= v < 2**63 for v in values)
    assert len(set(values)) == len(values)
    assert decision_seed(100000, 5) == decision_seed(100000, 5)
    words = np.random.SeedSequence([100000, 5]).generate_state(2, np.uint64)
    assert decision_seed(100000, 5) == int(words[0] ^ words[1]) & (2**63 - 1)
    for bad in (-1, 2**63, 1.0, True):
        with pytest.raises(ValueError):
            decision_seed(bad, 0)
        with pytest.raises(ValueError):
            decision_seed(0, bad)


def test_chunk_noise_is_the_documented_draw():
    noise = chunk_noise(123, 4)
    assert noise.dtype == np.float32 and noise.shape == (4, 12, 2)
    expected = np.random.default_rng(123).standard_normal((4, 12, 2), dtype=np.float32)
    np.testing.assert_array_equal(noise, expected)
    np.testing.assert_array_equal(chunk_noise(123, 4), noise)
    assert not np.array_equal(chunk_noise(124, 4), noise)
    assert chunk_noise(2**63 - 1, 1, horizon=3, action_dim=2).shape == (1, 3, 2)
    with pytest.raises(ValueError, match="batch"):
        chunk_noise(1, 0)


def test_summary_to_dict_is_json_ready():
    import json

    summary = run_episodes(chase_block, [5], num_envs=4, max_steps=12, env_factory=_gym_pusht_env)
    assert isinstance(summary, RolloutSummary) and summary.num_envs == 1
    d = json.loads(json.dumps(summary.to_dict()))
    assert d["seeds"] == [5] and d["decisions"] == 1 and len(d["episodes"]) == 1


def test_pad_rows_repeats_the_last_row_to_a_multiple_of_four():
    assert BATCH_MULTIPLE == 4
    x = np.arange(10, dtype=np.float32).reshape(5, 2)
    padded = pad_rows(x)
    assert padded.shape == (8, 2)
    np.testing.assert_array_equal(padded[:5], x)
    np.testing.assert_array_equal(padded[5:], np.repeat(x[-1:], 3, axis=0))
    assert pad_rows(padded) is padded


def test_row_noise_rows_are_their_own_seeds_draws():
    noise = row_noise([5, 7, 5])
    assert noise.shape == (3, 12, 2) and noise.dtype == np.float32
    np.testing.assert_array_equal(noise[1], chunk_noise(7, 1)[0])
    np.testing.assert_array_equal(noise[0], noise[2])
    with pytest.raises(ValueError, match="non-empty"):
        row_noise([])


def test_mean_steps_to_success_counts_only_the_successful_episodes() -> None:
    from pusht.results import EpisodeResult, RolloutSummary

    def summary(*episodes: tuple[int, bool]) -> RolloutSummary:
        results = [
            EpisodeResult(seed=i, max_reward=1.0 if ok else 0.5, success=ok, length=n, final_coverage=0.5)
            for i, (n, ok) in enumerate(episodes)
        ]
        return RolloutSummary.from_episodes(results, decisions=1, wall_time_s=0.0, num_envs=1, action_horizon=12, max_steps=300)

    both = summary((100, True), (140, True), (300, False))
    assert both.mean_steps_to_success == 120 and both.mean_length == pytest.approx(180)
    assert both.scores()["mean_steps_to_success"] == 120 and both.to_dict()["mean_steps_to_success"] == 120
    assert summary((300, False)).mean_steps_to_success is None

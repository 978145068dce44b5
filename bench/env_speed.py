"""Steps per second of our Push-T env (`pusht`) against gym-pusht 0.1.8, side by side in one run.

Both envs play the same seeds with the same actions: actions that keep pushing the block, recorded once
from our env and replayed open loop in both (the trajectories are identical, which is checked). The
envs take turns, in alternating order, for several repeats, so that a noisy machine slows both alike;
the medians over repeats are reported. Only `step` calls are timed.

    python bench/env_speed.py                 # 10 episodes x 300 steps, 5 repeats
    python bench/env_speed.py --wrapped       # both through gymnasium.make (TimeLimit, checkers)
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from dataclasses import dataclass

import numpy as np


@dataclass
class BenchConfig:
    episodes: int = 10
    """episodes per repeat (seeds seed .. seed + episodes - 1)"""
    steps: int = 300
    """steps per episode"""
    repeats: int = 5
    """times each env runs all episodes, alternating which env goes first"""
    seed: int = 0
    """first episode seed"""
    wrapped: bool = False
    """make both envs with gymnasium.make (with its wrappers) instead of using the env classes directly"""


def main(argv: list[str] | None = None) -> dict[str, float]:
    """Run the benchmark and print both envs' steps/s and their ratio."""
    cfg = parse_args(argv)
    envs = {"gym-pusht 0.1.8": _make_reference(cfg.wrapped), "pusht (ours)": _make_ours(cfg.wrapped)}
    seeds = list(range(cfg.seed, cfg.seed + cfg.episodes))
    actions = {seed: _pushing_actions(_make_ours(False), seed, cfg.steps) for seed in seeds}

    rates: dict[str, list[float]] = {name: [] for name in envs}
    finals: dict[str, np.ndarray] = {}
    order = list(envs)
    bar = _progress(cfg.repeats * len(envs))
    for repeat in range(cfg.repeats):
        for name in order if repeat % 2 == 0 else order[::-1]:
            seconds, finals[name] = _play(envs[name], seeds, actions)
            rates[name].append(len(seeds) * cfg.steps / seconds)
            bar.update(1)
    bar.close()

    ref_name, our_name = order
    ratios = [ours / ref for ours, ref in zip(rates[our_name], rates[ref_name])]
    max_diff = float(np.max(np.abs(finals[our_name] - finals[ref_name])))
    summary = {
        "reference_steps_per_s": statistics.median(rates[ref_name]),
        "ours_steps_per_s": statistics.median(rates[our_name]),
        "ratio": statistics.median(rates[our_name]) / statistics.median(rates[ref_name]),
        "max_final_state_diff": max_diff,
    }
    steps = cfg.episodes * cfg.steps
    how = "gymnasium.make" if cfg.wrapped else "bare env classes"
    print(f"Push-T env speed: {cfg.episodes} x {cfg.steps} = {steps} steps per env per repeat, x{cfg.repeats}, {how}")
    for name in order:
        runs = ", ".join(f"{r:,.0f}" for r in rates[name])
        print(f"  {name:<16} {statistics.median(rates[name]):>10,.0f} steps/s (median; runs: {runs})")
    spread = f"per-repeat range {min(ratios):.2f}x .. {max(ratios):.2f}x"
    print(f"  speed-up          {summary['ratio']:>10.2f}x ({spread})")
    print(f"  same trajectories: max |final state difference| = {max_diff:.1e}")
    return summary


def parse_args(argv: list[str] | None = None) -> BenchConfig:
    """The benchmark configuration from the command line."""
    defaults = BenchConfig()
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=defaults.episodes, help="episodes per repeat")
    parser.add_argument("--steps", type=int, default=defaults.steps, help="steps per episode")
    parser.add_argument("--repeats", type=int, default=defaults.repeats, help="runs of all episodes per env, alternating order")
    parser.add_argument("--seed", type=int, default=defaults.seed, help="first episode seed")
    parser.add_argument("--wrapped", action="store_true", help="make both envs with gymnasium.make (with wrappers)")
    args = parser.parse_args(argv)
    for name in ("episodes", "steps", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be at least 1")
    return BenchConfig(**vars(args))


def _make_reference(wrapped: bool):
    try:
        import gym_pusht  # noqa: F401  (registers gym_pusht/PushT-v0)
        import gymnasium
    except ImportError:
        sys.exit("gym-pusht is not installed: pip install -e '.[test]' (it pins gym-pusht==0.1.8)")
    env = gymnasium.make("gym_pusht/PushT-v0", obs_type="state", render_mode="rgb_array")
    return env if wrapped else env.unwrapped


def _make_ours(wrapped: bool):
    import gymnasium

    import pusht

    return gymnasium.make(pusht.ENV_ID) if wrapped else pusht.PushTEnv()


def _pushing_actions(env, seed: int, steps: int) -> np.ndarray:
    """Actions aimed just beyond the block's centre, plus noise: the agent keeps pushing the block."""
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    actions = np.empty((steps, 2), dtype=np.float32)
    for t in range(steps):
        cog = obs[2:4] + 45.0 * np.array([-math.sin(obs[4]), math.cos(obs[4])])
        actions[t] = np.clip(cog + 0.15 * (cog - obs[:2]) + rng.normal(0.0, 20.0, 2), 0.0, 512.0)
        obs, *_ = env.step(actions[t])
    return actions


def _play(env, seeds: list[int], actions: dict[int, np.ndarray]) -> tuple[float, np.ndarray]:
    """Seconds spent in step() over all episodes, and each episode's final observation."""
    elapsed = 0.0
    finals = []
    clock = time.perf_counter
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        episode = actions[seed]
        step = env.step
        start = clock()
        for action in episode:
            obs = step(action)[0]
        elapsed += clock() - start
        finals.append(np.asarray(obs, dtype=np.float64))
    return elapsed, np.stack(finals)


def _progress(total: int):
    try:
        from tqdm import tqdm
    except ImportError:  # tqdm comes with the train/test extras; the bench runs without it
        return _NoBar()
    return tqdm(total=total, desc="env runs", unit="run", file=sys.stderr)


class _NoBar:
    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


if __name__ == "__main__":
    main()

"""Evaluation of a BabyAI policy in GoToLocal, and bot demonstrations.

BabyAI GoToLocal (``BabyAI-GoToLocalS8N7-v0``: room size 8, 7 objects), fully observed 8x8x3 grid encoding
with the agent written in. Episode k is reset with seed ``seed + k``; success means the task is completed
within ``max_steps`` steps; actions are greedy, so one policy always gets the same score.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from minigrid.envs.babyai import GoToLocal
from minigrid.utils.baby_ai_bot import BabyAIBot

from playseg_core.augment.policy import InstructionPolicy, PolicyEvaluation, torch_threads
from playseg_core.data.features import STATE
from playseg_core.domains.babyai.imitation import Demonstration
from playseg_core.domains.babyai.play import PlayConfig, encode_state, make_env, quiet_level_generation


def make_goto_env(room_size: int = 8, num_objects: int = 7) -> GoToLocal:
    """BabyAI GoToLocal; (8, 7) is ``BabyAI-GoToLocalS8N7-v0`` (built directly: no gym wrappers).

    The play generator's environment (`play.make_env`): its own step limit is disabled, so an episode
    ends where the caller's ``max_steps`` says, not at the level's default limit (64 steps for 8x8).
    """
    return make_env(PlayConfig(num_objects=num_objects, room_size=room_size))


def reset_quietly(env: GoToLocal, seed: int) -> None:
    """Reset with a seed, swallowing what level generation prints to stdout."""
    with quiet_level_generation():
        env.reset(seed=seed)


def bot_demonstrations(
    num: int, seed: int, room_size: int = 8, num_objects: int = 7, max_steps: int = 64
) -> list[Demonstration]:
    """``num`` GoToLocal episodes solved by minigrid's BabyAIBot; episode k is reset with ``seed + k``.

    Returns (instruction, states (L+1, 8, 8, 3) uint8, actions (L,) int64) per successful episode (the
    bot solves GoToLocal always; a failure would be dropped rather than taught).
    """
    env = make_goto_env(room_size, num_objects)
    demonstrations: list[Demonstration] = []
    for k in range(num):
        reset_quietly(env, seed + k)
        bot = BabyAIBot(env)
        bot.vis_mask[:] = True  # full observability: the bot needs no exploration
        states, actions = [encode_state(env)], []
        success = False
        for _ in range(max_steps):
            action = int(bot.replan())
            _, reward, terminated, truncated, _ = env.step(action)
            states.append(encode_state(env))
            actions.append(action)
            if terminated or truncated:
                success = terminated and reward > 0
                break
        if success:
            demonstrations.append((env.mission, np.stack(states), np.array(actions, dtype=np.int64)))
    return demonstrations


# ---------------------------------------------------------------------------------------------------------
# Evaluation


class RandomPolicy:
    """Uniform random actions among left/right/forward (the moves that matter in GoToLocal); a baseline."""

    def __init__(self, seed: int = 0):
        self.rng = np.random.default_rng(seed)

    def act(self, observations: Mapping[str, np.ndarray], instructions: Sequence[str]) -> np.ndarray:
        return self.rng.integers(0, 3, len(instructions))


@dataclass
class EvalResult(PolicyEvaluation):
    mean_success_steps: float = float("nan")  # steps taken in successful episodes (nan if none)
    episode_steps: list[int] = field(default_factory=list)  # steps until success, or max_steps on failure


def evaluate_policy(
    model: InstructionPolicy,
    num_episodes: int = 512,
    max_steps: int = 25,
    seed: int = 0,
    num_envs: int = 128,
    room_size: int = 8,
    num_objects: int = 7,
    num_threads: int = 1,
) -> EvalResult:
    """Success rate on the fixed episodes seed, seed+1, ..., run ``num_envs`` at a time.

    Each step stacks the states of all running episodes into one batch for a single forward pass.
    """
    started = time.perf_counter()
    envs = [make_goto_env(room_size, num_objects) for _ in range(min(num_envs, num_episodes))]
    success = [False] * num_episodes
    steps_taken = [max_steps] * num_episodes
    instructions = [""] * num_episodes
    for wave_start in range(0, num_episodes, len(envs)):
        episodes = list(range(wave_start, min(wave_start + len(envs), num_episodes)))
        for slot, episode in enumerate(episodes):
            reset_quietly(envs[slot], seed + episode)
            instructions[episode] = envs[slot].mission
        running = list(range(len(episodes)))  # slots still going
        for step in range(max_steps):
            states = np.stack([encode_state(envs[slot]) for slot in running])
            with torch_threads(num_threads):
                actions = model.act({STATE: states}, [envs[slot].mission for slot in running])
            still_running = []
            for slot, action in zip(running, actions, strict=True):
                _, reward, terminated, truncated, _ = envs[slot].step(int(action))
                if terminated and reward > 0:
                    success[episodes[slot]] = True
                    steps_taken[episodes[slot]] = step + 1
                elif not (terminated or truncated):
                    still_running.append(slot)
            running = still_running
            if not running:
                break
    successes = sum(success)
    success_steps = [s for s, ok in zip(steps_taken, success, strict=True) if ok]
    return EvalResult(
        success_rate=successes / num_episodes,
        num_episodes=num_episodes,
        num_successes=successes,
        mean_success_steps=float(np.mean(success_steps)) if success_steps else float("nan"),
        seconds=time.perf_counter() - started,
        seed=seed,
        episode_success=success,
        episode_steps=steps_taken,
        episode_instructions=instructions,
    )

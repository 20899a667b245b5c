"""BabyAI play: a scripted bot solving "go to" tasks one after another in one GoToLocal room.

One reset per episode, then up to ``max_tasks`` tasks in a row. Each task's goal is an object in the
room whose (type, colour) differs from the previous goal; a fresh ``BabyAIBot`` with full visibility
solves it. Every step records the full-view RGB frame, the symbolic grid state and the action; every
solved task becomes one ground-truth segment labelled with its instruction.

Instruction article: minigrid's own surface form is used, so a goal is "the red ball" when it is the
only red ball in the room and "a red ball" when there are several (any of them completes the task).
"""

from __future__ import annotations

import contextlib
import io
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import ACTION, STATE, Feature, Features
from playseg_core.domains.babyai.spec import (
    CAMERA,
    INSTRUCTIONS,
    NUM_ACTIONS,
    OBJECT_TYPES,
    STEPS_PER_SECOND,
)
from playseg_core.errors import PlaysegError

# pygame (imported by minigrid) prints a banner to stdout on import unless told not to.
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
with contextlib.redirect_stdout(io.StringIO()):
    from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX
    from minigrid.envs.babyai.core.verifier import GoToInstr, ObjDesc
    from minigrid.envs.babyai.goto import GoToLocal
    from minigrid.utils.baby_ai_bot import BabyAIBot

# The env's own step limit would truncate long play episodes; our per-task limit replaces it.
_UNLIMITED_ENV_STEPS = 2**31 - 1


@dataclass(frozen=True)
class PlayConfig:
    """How BabyAI play episodes are generated.

    max_task_steps: a task the bot has not finished after this many steps counts as failed (bot stuck);
    the episode then ends after the last solved task.
    """

    num_objects: int = 7
    room_size: int = 8
    max_tasks: int = 10
    tile_size: int = 8
    max_task_steps: int = 64

    def __post_init__(self) -> None:
        if self.room_size < 4:
            raise PlaysegError(f"PlayConfig.room_size must be >= 4, got {self.room_size}")
        if self.num_objects < 2:
            raise PlaysegError(
                f"PlayConfig.num_objects must be >= 2 (goals must change), got {self.num_objects}"
            )
        if self.max_tasks < 1 or self.max_task_steps < 1 or self.tile_size < 1:
            raise PlaysegError("PlayConfig.max_tasks, max_task_steps and tile_size must be >= 1")

    @property
    def frame_shape(self) -> tuple[int, int, int]:
        side = self.room_size * self.tile_size
        return (side, side, 3)

    @property
    def state_shape(self) -> tuple[int, int, int]:
        return (self.room_size, self.room_size, 3)

    @property
    def features(self) -> Features:
        """The dataset features of this play: the top camera, the symbolic grid state, a discrete action."""
        return Features.of(
            [
                Feature(CAMERA, "image", "uint8", self.frame_shape),
                # minigrid's grid encoding, indexed [x, y]: (object type, colour, state) per cell.
                Feature(STATE, "state", "uint8", self.state_shape),
                Feature(ACTION, "action", "float32", (1,), num_values=NUM_ACTIONS),
            ],
            fps=STEPS_PER_SECOND,
        )


@contextlib.contextmanager
def quiet_level_generation() -> Any:
    """Swallow what minigrid prints to stdout while generating a level ("Sampling rejected: ...")."""
    with contextlib.redirect_stdout(io.StringIO()):
        yield


def make_env(config: PlayConfig, seed: int | None = None) -> GoToLocal:
    """A GoToLocal room with ``config.num_objects`` objects, reset with ``seed``, step limit disabled."""
    with quiet_level_generation():
        env = GoToLocal(
            room_size=config.room_size,
            num_dists=config.num_objects,
            max_steps=_UNLIMITED_ENV_STEPS,
        )
        env.reset(seed=seed)
    return env


def render_frame(env: GoToLocal, tile_size: int) -> np.ndarray:
    """Full-view RGB frame without the field-of-view highlight, (H, W, 3) uint8.

    Renders the grid directly: equal to ``env.get_frame(highlight=False, tile_size=...)`` without the
    visibility computation that the highlight would need.
    """
    env = env.unwrapped
    return env.grid.render(tile_size, env.agent_pos, env.agent_dir, highlight_mask=None)


def encode_state(env: GoToLocal) -> np.ndarray:
    """``grid.encode()`` (width, height, 3) uint8 with the agent placed in it.

    The agent's cell is (10 = agent, 0 = red, direction), as in minigrid's fully observable wrapper.
    """
    env = env.unwrapped
    state = env.grid.encode()
    x, y = env.agent_pos
    state[x, y] = (OBJECT_TO_IDX["agent"], COLOR_TO_IDX["red"], env.agent_dir)
    return state


def room_objects(env: GoToLocal) -> list[Any]:
    """Objects a goal can name (boxes, balls, keys) lying in the grid, in row-major grid order."""
    return [cell for cell in env.unwrapped.grid.grid if cell is not None and cell.type in OBJECT_TYPES]


def set_goal(env: GoToLocal, obj_type: str, colour: str) -> str:
    """Make "go to <colour> <type>" the env's mission and return its instruction string."""
    unwrapped = env.unwrapped
    unwrapped.instrs = GoToInstr(ObjDesc(obj_type, colour))
    # The verifier binds the matching objects and the env; without this the task never succeeds.
    unwrapped.instrs.reset_verifier(unwrapped)
    instruction = unwrapped.instrs.surface(unwrapped)
    unwrapped.mission = instruction
    if instruction not in INSTRUCTIONS:
        raise PlaysegError(f"goal produced instruction {instruction!r}, which is not one of INSTRUCTIONS")
    return instruction


def episode_id_for_seed(seed: int) -> str:
    """The id of the play episode generated from ``seed``."""
    return f"babyai-{seed}"


def generate_episode(config: PlayConfig, seed: int) -> Episode:
    """One deterministic play episode (same config and seed -> identical arrays and segments).

    The episode may hold fewer than ``max_tasks`` segments when the bot gets stuck; it holds zero
    steps when the very first task fails.
    """
    env = make_env(config, seed)
    rng = np.random.default_rng(seed)
    frames = [render_frame(env, config.tile_size)]
    states = [encode_state(env)]
    actions: list[int] = []
    segments: list[Segment] = []
    previous_goal: tuple[str, str] | None = None

    for _ in range(config.max_tasks):
        candidates = [obj for obj in room_objects(env) if (obj.type, obj.color) != previous_goal]
        if not candidates:
            break
        goal = candidates[int(rng.integers(len(candidates)))]
        previous_goal = (goal.type, goal.color)
        instruction = set_goal(env, goal.type, goal.color)
        bot = BabyAIBot(env)
        bot.vis_mask[:] = True  # full visibility: the bot plans on the whole room, no exploration

        task_frames: list[np.ndarray] = []
        task_states: list[np.ndarray] = []
        task_actions: list[int] = []
        solved = False
        while len(task_actions) < config.max_task_steps:
            action = int(bot.replan())
            _, _, terminated, _, _ = env.step(action)
            task_actions.append(action)
            task_frames.append(render_frame(env, config.tile_size))
            task_states.append(encode_state(env))
            if terminated:
                solved = True
                break
        if not solved:
            break  # a stuck bot ends the episode after the last solved task
        start = len(actions)
        actions.extend(task_actions)
        frames.extend(task_frames)
        states.extend(task_states)
        segments.append(Segment(start, len(actions), instruction))

    return Episode(
        episode_id=episode_id_for_seed(seed),
        actions=np.asarray(actions, dtype=np.float32).reshape(-1, 1),
        images={CAMERA: np.stack(frames).astype(np.uint8, copy=False)},
        state=np.stack(states).astype(np.uint8, copy=False),
        segments=segments,
    )

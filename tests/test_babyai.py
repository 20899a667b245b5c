"""BabyAI play generation: shapes, determinism, ground truth checked by replaying the real env, silence."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from playseg_core.domains.babyai.play import (
    PlayConfig,
    encode_state,
    generate_episode,
    make_env,
    render_frame,
)
from playseg_core.domains.babyai.spec import CAMERA, INSTRUCTIONS

CONFIG = PlayConfig(max_tasks=4)
REJECTING_SEED = 48  # minigrid rejects a sampled level for this seed and prints about it


@pytest.fixture(scope="module")
def episode():
    return generate_episode(CONFIG, seed=3)


def test_instructions_are_the_36_goto_strings_in_fixed_order() -> None:
    assert len(INSTRUCTIONS) == 36 == len(set(INSTRUCTIONS))
    assert INSTRUCTIONS[0] == "go to the red box"
    assert INSTRUCTIONS[1] == "go to the red ball"
    assert INSTRUCTIONS[17] == "go to the grey key"
    assert INSTRUCTIONS[18] == "go to a red box"
    for text in INSTRUCTIONS:
        words = text.split()
        assert words[:2] == ["go", "to"] and words[2] in ("the", "a") and len(words) == 5


def test_episode_shapes_and_dtypes(episode) -> None:
    steps = episode.num_steps
    assert steps > 0
    assert list(episode.images) == [CAMERA]  # the one camera: the room seen from above
    frames = episode.images[CAMERA]
    assert frames.shape == (steps + 1, 64, 64, 3) and frames.dtype == np.uint8
    assert episode.state.shape == (steps + 1, 8, 8, 3) and episode.state.dtype == np.uint8
    assert episode.actions.shape == (steps, 1) and episode.actions.dtype == np.float32
    assert set(np.unique(episode.actions)) <= set(range(7))


def test_segments_tile_the_episode_and_goals_change(episode) -> None:
    segments = episode.segments
    assert 1 <= len(segments) <= CONFIG.max_tasks
    assert segments[0].start == 0 and segments[-1].end == episode.num_steps
    for before, after in zip(segments, segments[1:], strict=False):
        assert before.end == after.start
        assert before.instruction.split()[3:] != after.instruction.split()[3:]
    assert all(seg.instruction in INSTRUCTIONS for seg in segments)


def test_replaying_actions_reproduces_observations_and_reaches_each_goal(episode) -> None:
    env = make_env(CONFIG, seed=3)
    assert np.array_equal(render_frame(env, 8), env.get_frame(highlight=False, tile_size=8))
    frames = episode.images[CAMERA]
    assert np.array_equal(frames[0], render_frame(env, 8))
    assert np.array_equal(episode.state[0], encode_state(env))
    ends = {seg.end: seg for seg in episode.segments}
    for t, action in enumerate(episode.actions[:, 0].astype(int), start=1):
        env.step(action)
        assert np.array_equal(frames[t], env.get_frame(highlight=False, tile_size=8)), f"frame {t}"
        assert np.array_equal(episode.state[t], encode_state(env)), f"state {t}"
        if t in ends:
            _, article, colour, obj_type = ends[t].instruction.split()[1:]
            facing = env.grid.get(*env.front_pos)
            assert facing is not None and (facing.type, facing.color) == (obj_type, colour), f"step {t}"
            same = [o for o in env.grid.grid if o is not None and (o.type, o.color) == (obj_type, colour)]
            assert article == ("the" if len(same) == 1 else "a")


def test_state_places_the_agent_with_its_direction(episode) -> None:
    env = make_env(CONFIG, seed=3)
    agent_cells = np.argwhere(episode.state[0][:, :, 0] == 10)
    assert agent_cells.tolist() == [list(env.agent_pos)]
    x, y = env.agent_pos
    assert episode.state[0][x, y, 2] == env.agent_dir
    for state in episode.state:
        assert (state[:, :, 0] == 10).sum() == 1


def test_same_seed_gives_identical_bytes_and_other_seed_differs(episode) -> None:
    again = generate_episode(CONFIG, seed=3)
    assert again.images[CAMERA].tobytes() == episode.images[CAMERA].tobytes()
    assert again.state.tobytes() == episode.state.tobytes()
    assert again.actions.tobytes() == episode.actions.tobytes()
    assert again.segments == episode.segments
    other = generate_episode(CONFIG, seed=4)
    assert other.actions.tobytes() != episode.actions.tobytes() or other.segments != episode.segments


def test_long_episodes_are_not_cut_by_the_env_step_limit() -> None:
    config = PlayConfig(max_tasks=30)
    episode = generate_episode(config, seed=0)
    assert len(episode.segments) == 30
    assert episode.num_steps > 64  # GoToLocal's own limit for an 8x8 room would have ended it at 64


def test_a_stuck_bot_ends_the_episode_after_the_last_solved_task() -> None:
    config = PlayConfig(max_task_steps=1)
    episode = generate_episode(config, seed=3)
    full = generate_episode(PlayConfig(), seed=3)
    solved_in_one = 0
    for seg in full.segments:
        if seg.length != 1:
            break
        solved_in_one += 1
    assert len(episode.segments) == solved_in_one
    assert episode.num_steps == solved_in_one
    assert all(seg.length == 1 for seg in episode.segments)


def test_invalid_config_is_rejected() -> None:
    with pytest.raises(ValueError, match="num_objects"):
        PlayConfig(num_objects=1)


def _run_python(code: str) -> subprocess.CompletedProcess[bytes]:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=120, check=True)


@pytest.mark.slow
def test_generation_prints_nothing_to_stdout() -> None:
    # The same level made by plain minigrid does print (so the check below is not vacuous).
    raw = _run_python(
        "import os; os.environ['PYGAME_HIDE_SUPPORT_PROMPT'] = '1'\n"
        "from minigrid.envs.babyai.goto import GoToLocal\n"
        f"GoToLocal(room_size=8, num_dists=7).reset(seed={REJECTING_SEED})\n"
    )
    assert b"Sampling rejected" in raw.stdout
    ours = _run_python(
        "from playseg_core.domains.babyai.play import PlayConfig, generate_episode\n"
        f"episode = generate_episode(PlayConfig(max_tasks=2), seed={REJECTING_SEED})\n"
        "assert episode.num_steps > 0\n"
    )
    assert ours.stdout == b""

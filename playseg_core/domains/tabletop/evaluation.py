"""Evaluation of an instruction-following policy in the tabletop simulator.

Episode k of an evaluation with ``seed`` starts from a random layout and one task of the task set drawn
as play draws them (instructions.py `TaskSet`: for ``all``, a family uniformly among those with a task
that may be given, then one of its tasks; for ``calvin``, one of its tasks uniformly), both from
the generator ``default_rng([seed + k, EVALUATION_STREAM])``: a stream of its own, never a play
episode's layout. The policy sees what the dataset recorded (the rendered camera frame and the state
vector, the same features) and its action drives the simulator for one control step; the episode
succeeds when the task oracle says done within ``max_steps`` (spec.EVAL_STEP_BUDGET by default).
Episodes run in lockstep batches (one forward pass per step for all running episodes) in a fixed order,
so the same deterministic policy always gets the same score.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from playseg_core.augment.policy import InstructionPolicy, PolicyEvaluation, torch_threads
from playseg_core.data.features import STATE
from playseg_core.domains.tabletop.instructions import TASK_SETS, Task, TaskSet, is_done
from playseg_core.domains.tabletop.play import draw_task
from playseg_core.domains.tabletop.render import Renderer
from playseg_core.domains.tabletop.sim import Scene, TabletopSim
from playseg_core.domains.tabletop.spec import CAMERA, DEFAULT_IMAGE_SIZE, EVAL_STEP_BUDGET, MAX_SPEED
from playseg_core.errors import PlaysegError

EVALUATION_STREAM = 7_000_001
"""Second word of an evaluation episode's seed sequence: keeps its layouts apart from play's."""


@dataclass(frozen=True)
class EvaluationEpisode:
    """One start: the generator seed it came from and the task to carry out."""

    seed: int
    task: Task


def evaluation_start(seed: int, tasks: TaskSet = TASK_SETS["all"]) -> tuple[TabletopSim, EvaluationEpisode]:
    """The simulator at the start of the evaluation episode of ``seed``, and its task (of ``tasks``)."""
    rng = np.random.default_rng([seed, EVALUATION_STREAM])
    while True:  # a layout always has tasks to give; the loop only guards a (never seen) empty draw
        sim = TabletopSim()
        sim.place_randomly(rng)
        task = draw_task(sim.scene(), rng, tasks=tasks)
        if task is not None:
            return sim, EvaluationEpisode(seed, task)


def evaluation_episodes(
    num_episodes: int, seed: int, tasks: TaskSet = TASK_SETS["all"]
) -> list[EvaluationEpisode]:
    """The starts ``seed``, ``seed + 1``, ... of an evaluation (to report what it asks per family)."""
    return [evaluation_start(seed + k, tasks)[1] for k in range(num_episodes)]


@dataclass
class TabletopEvaluation(PolicyEvaluation):
    """Success overall and by instruction family, and the steps each episode took."""

    family_success: dict[str, tuple[int, int]] = field(default_factory=dict)  # family -> (done, given)
    episode_steps: list[int] = field(default_factory=list)  # steps until done, or max_steps on failure
    max_steps: int = EVAL_STEP_BUDGET


class _Running:
    """One evaluation episode being run."""

    def __init__(self, index: int, seed: int, renderer: Renderer, tasks: TaskSet) -> None:
        self.index = index
        self.sim, self.episode = evaluation_start(seed, tasks)
        self.start: Scene = self.sim.scene()
        self.renderer = renderer

    def observe(self) -> tuple[np.ndarray, np.ndarray]:
        return self.renderer.render(self.sim.scene()), self.sim.state_vector()


def evaluate_policy(
    policy: InstructionPolicy,
    num_episodes: int,
    seed: int,
    max_steps: int = EVAL_STEP_BUDGET,
    image_size: int = DEFAULT_IMAGE_SIZE,
    batch_episodes: int = 64,
    num_threads: int = 1,
    tasks: TaskSet = TASK_SETS["all"],
) -> TabletopEvaluation:
    """Success rate of ``policy`` on the evaluation episodes of seeds ``seed .. seed + num_episodes - 1``
    (tasks of ``tasks``), ``batch_episodes`` at a time; ValueError on a non-positive count, budget or
    batch."""
    if num_episodes < 1 or max_steps < 1 or batch_episodes < 1:
        raise PlaysegError(
            f"tabletop evaluation: num_episodes, max_steps and batch_episodes must be >= 1, got "
            f"{num_episodes}, {max_steps}, {batch_episodes}"
        )
    started = time.perf_counter()
    renderer = Renderer(image_size)
    success = [False] * num_episodes
    steps_taken = [max_steps] * num_episodes
    instructions = [""] * num_episodes
    families: dict[str, list[int]] = {}
    for wave in range(0, num_episodes, batch_episodes):
        running = [
            _Running(k, seed + k, renderer, tasks)
            for k in range(wave, min(wave + batch_episodes, num_episodes))
        ]
        for run in running:
            families.setdefault(run.episode.task.family, [0, 0])[1] += 1
            instructions[run.index] = run.episode.task.text
        for step in range(max_steps):
            frames, states = zip(*(run.observe() for run in running), strict=True)
            observations: Mapping[str, np.ndarray] = {CAMERA: np.stack(frames), STATE: np.stack(states)}
            with torch_threads(num_threads):
                actions = np.asarray(policy.act(observations, [run.episode.task.text for run in running]))
            actions = np.clip(actions.reshape(len(running), 2), -MAX_SPEED, MAX_SPEED)
            still_running = []
            for run, action in zip(running, actions, strict=True):
                run.sim.step(action)
                if is_done(run.episode.task, run.sim.scene(), run.start):
                    success[run.index] = True
                    steps_taken[run.index] = step + 1
                    families[run.episode.task.family][0] += 1
                else:
                    still_running.append(run)
            running = still_running
            if not running:
                break
    successes = sum(success)
    return TabletopEvaluation(
        success_rate=successes / num_episodes,
        num_episodes=num_episodes,
        num_successes=successes,
        seed=seed,
        seconds=time.perf_counter() - started,
        episode_success=success,
        episode_instructions=instructions,
        family_success={name: (done, given) for name, (done, given) in sorted(families.items())},
        episode_steps=steps_taken,
        max_steps=max_steps,
    )


class ScriptedPolicy:
    """Moves the effector straight towards a fixed point (a baseline and a test double: it completes
    `effector_to_region` tasks whose region holds that point, and little else)."""

    def __init__(self, target: Sequence[float]) -> None:
        self.target = np.asarray(target, np.float32)

    def act(self, observations: Mapping[str, np.ndarray], instructions: Sequence[str]) -> np.ndarray:
        position = np.asarray(observations[STATE], np.float32)[:, :2]
        return np.clip((self.target - position) * 2.0, -MAX_SPEED, MAX_SPEED).astype(np.float32)


__all__ = [
    "EVALUATION_STREAM",
    "EvaluationEpisode",
    "ScriptedPolicy",
    "TabletopEvaluation",
    "evaluate_policy",
    "evaluation_episodes",
    "evaluation_start",
]

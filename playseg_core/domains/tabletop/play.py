"""Tabletop play: long episodes in which the teleoperator carries out one instruction after another.

One random layout per episode, then tasks in a row until the episode has its number of solved tasks.
Each next instruction is drawn among those that may be given now (not already done, worth doing: see
instructions.py), first a family uniformly among the families with such tasks, then a task of it,
never the one just attempted. Every step records the camera frame, the proprioceptive state and the
commanded velocity.

Ground truth: every solved task is one segment labelled with its instruction, ending at the step where
the oracle first says done. Steps no segment covers are unlabelled: short idle stretches between tasks
(pauses, aimless moves), and the steps of a task the teleoperator failed within `max_task_steps` (they
stay in the recording, as an operator's fumbling would, but carry no label). After `max_failures`
failures in a row the episode ends.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import ACTION, STATE, Feature, Features
from playseg_core.domains.tabletop.instructions import (
    TASK_SETS,
    Task,
    TaskSet,
    applicable_tasks,
    is_done,
    task_set,
)
from playseg_core.domains.tabletop.render import Renderer
from playseg_core.domains.tabletop.sim import Scene, TabletopSim
from playseg_core.domains.tabletop.spec import (
    ACTION_HIGH,
    ACTION_LOW,
    ACTION_NAMES,
    CAMERA,
    CONTROL_HZ,
    DEFAULT_IMAGE_SIZE,
    STATE_NAMES,
)
from playseg_core.domains.tabletop.teleop import TeleopConfig, Teleoperator
from playseg_core.errors import PlaysegError


@dataclass(frozen=True)
class PlayConfig:
    """How tabletop play episodes are generated.

    tasks_per_episode: (low, high) solved tasks per episode, drawn uniformly.
    max_task_steps: a task not done after this many steps counts as failed (its steps stay unlabelled).
    max_failures: failed tasks in a row that end the episode.
    idle_chance: chance of an unlabelled stretch before each task; idle_steps: its (low, high) length.
    task_set: the instructions play gives (instructions.py `TASK_SETS`: ``all`` or ``calvin``).
    """

    image_size: int = DEFAULT_IMAGE_SIZE
    tasks_per_episode: tuple[int, int] = (10, 20)
    max_task_steps: int = 120
    max_failures: int = 2
    idle_chance: float = 0.1
    idle_steps: tuple[int, int] = (5, 15)
    teleop: TeleopConfig = field(default_factory=TeleopConfig)
    task_set: str = "all"

    def __post_init__(self) -> None:
        Renderer(self.image_size)  # ValueError naming a bad image size
        task_set(self.task_set)  # ValueError naming an unknown set
        low, high = self.tasks_per_episode
        if not 1 <= low <= high:
            raise PlaysegError(f"PlayConfig.tasks_per_episode must be 1 <= low <= high, got {(low, high)}")
        if self.max_task_steps < 1 or self.max_failures < 1:
            raise PlaysegError("PlayConfig.max_task_steps and max_failures must be >= 1")
        if not 0.0 <= self.idle_chance <= 1.0:
            raise PlaysegError(f"PlayConfig.idle_chance must be in [0, 1], got {self.idle_chance}")
        if not 1 <= self.idle_steps[0] <= self.idle_steps[1]:
            raise PlaysegError(f"PlayConfig.idle_steps must be 1 <= low <= high, got {self.idle_steps}")

    @classmethod
    def from_json(cls, raw: Mapping[str, Any], where: str = "play_config") -> PlayConfig:
        """The config ``asdict(config)`` was written from (a dataset's ``meta.play_config``); ValueError
        naming ``where`` and the field for anything else."""
        if not isinstance(raw, Mapping):
            raise PlaysegError(f"{where}: expected a mapping of PlayConfig fields, got {type(raw).__name__}")
        settings = _settings(cls, raw, where)
        if "teleop" in settings:
            teleop = settings["teleop"]
            if not isinstance(teleop, Mapping):
                raise PlaysegError(f"{where}.teleop: expected a mapping of TeleopConfig fields")
            try:
                settings["teleop"] = TeleopConfig(**_settings(TeleopConfig, teleop, f"{where}.teleop"))
            except TypeError as error:
                raise PlaysegError(f"{where}.teleop: {error}") from error
        try:
            return cls(**settings)
        except TypeError as error:  # a value of the wrong type
            raise PlaysegError(f"{where}: {error}") from error

    @property
    def tasks(self) -> TaskSet:
        """The task set play draws from."""
        return task_set(self.task_set)

    @property
    def instructions(self) -> tuple[str, ...]:
        """The instructions a dataset of this play lists (its instruction index is the position here)."""
        return self.tasks.instructions

    @property
    def features(self) -> Features:
        """The dataset features: the top camera, the effector state, the commanded velocity."""
        side = self.image_size
        return Features.of(
            [
                Feature(CAMERA, "image", "uint8", (side, side, 3)),
                Feature(STATE, "state", "float32", (len(STATE_NAMES),), names=STATE_NAMES),
                Feature(
                    ACTION, "action", "float32", (2,), names=ACTION_NAMES, low=ACTION_LOW, high=ACTION_HIGH
                ),
            ],
            fps=CONTROL_HZ,
        )


def _settings(kind: type, raw: Mapping[str, Any], where: str) -> dict[str, Any]:
    """``raw``'s entries as keyword arguments of the dataclass ``kind`` (JSON lists back to tuples)."""
    known = {f.name for f in fields(kind)}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise PlaysegError(
            f"{where}: unknown field {unknown[0]!r} (a {kind.__name__} has {', '.join(sorted(known))})"
        )
    return {name: tuple(value) if isinstance(value, list) else value for name, value in raw.items()}


@dataclass
class PlayStats:
    """What the teleoperator did in one episode: attempted, solved and failed tasks (by family),
    the steps of each solved task, the unlabelled idle steps."""

    attempted: dict[str, int] = field(default_factory=dict)
    solved: dict[str, int] = field(default_factory=dict)
    task_lengths: list[int] = field(default_factory=list)
    failed_steps: int = 0
    idle_steps: int = 0

    def count(self, task: Task, solved: bool) -> None:
        self.attempted[task.family] = self.attempted.get(task.family, 0) + 1
        if solved:
            self.solved[task.family] = self.solved.get(task.family, 0) + 1

    def merge(self, other: PlayStats) -> None:
        for family, n in other.attempted.items():
            self.attempted[family] = self.attempted.get(family, 0) + n
        for family, n in other.solved.items():
            self.solved[family] = self.solved.get(family, 0) + n
        self.task_lengths.extend(other.task_lengths)
        self.failed_steps += other.failed_steps
        self.idle_steps += other.idle_steps

    @property
    def success_rate(self) -> float:
        attempted = sum(self.attempted.values())
        return sum(self.solved.values()) / attempted if attempted else 0.0

    def to_json(self) -> dict[str, object]:
        return {
            "attempted": dict(sorted(self.attempted.items())),
            "solved": dict(sorted(self.solved.items())),
            "success_rate": round(self.success_rate, 4),
            "failed_steps": self.failed_steps,
            "idle_steps": self.idle_steps,
        }


@dataclass
class PlayEpisode:
    """One generated episode and what the teleoperator did in it."""

    episode: Episode
    stats: PlayStats


class Recorder:
    """Runs the sim step by step and keeps every observation (frame, state) and applied action.

    Subclasses change what is kept through `observe` (after the start and every step) and `apply`.
    """

    def __init__(self, sim: TabletopSim, renderer: Renderer) -> None:
        self.sim, self.renderer = sim, renderer
        self.scene = sim.scene()
        self.frames: list[np.ndarray] = []
        self.states: list[np.ndarray] = []
        self.actions: list[tuple[float, float]] = []
        self.observe()

    @property
    def steps(self) -> int:
        return len(self.actions)

    def apply(self, action: np.ndarray) -> tuple[float, float]:
        """Steps the sim with ``action``; the command it applied (clipped)."""
        return self.sim.step(action)

    def observe(self) -> None:
        """Keeps the observation of ``self.scene``, just reached: its frame and the state vector."""
        self.frames.append(self.renderer.render(self.scene))
        self.states.append(self.sim.state_vector())

    def step(self, action: np.ndarray) -> Scene:
        self.actions.append(self.apply(action))
        self.scene = self.sim.scene()
        self.observe()
        return self.scene


_EPISODE_PREFIX = "tabletop-"


def episode_id_for_seed(seed: int) -> str:
    """The id of the play episode generated from ``seed``."""
    return f"{_EPISODE_PREFIX}{seed}"


def seed_of_episode(episode_id: str) -> int:
    """The seed the play episode ``episode_id`` was generated from (`episode_id_for_seed`'s inverse)."""
    seed = episode_id.removeprefix(_EPISODE_PREFIX)
    if seed == episode_id or not seed.isdigit():
        raise PlaysegError(
            f"episode {episode_id!r}: not a generated tabletop episode ({_EPISODE_PREFIX}<seed>)"
        )
    return int(seed)


class SceneRecorder(Recorder):
    """Keeps the scene after every step and renders nothing: what the task oracle reads in a replay."""

    def __init__(self, sim: TabletopSim, renderer: Renderer) -> None:
        self.scenes: list[Scene] = []
        super().__init__(sim, renderer)

    def observe(self) -> None:
        self.scenes.append(self.scene)


def replay_scenes(
    config: PlayConfig, episode_id: str, actions: np.ndarray | None = None
) -> tuple[list[Scene], list[Segment]]:
    """The T+1 scenes and the true segments of the play episode ``episode_id``, played again from its
    seed (play is deterministic). ``actions``, the episode's recorded commands, are checked against the
    replay's: ValueError naming the episode when they differ (another play config or domain version)."""
    recording, segments, _ = play(config, seed_of_episode(episode_id), SceneRecorder)
    assert isinstance(recording, SceneRecorder)
    replayed = np.asarray(recording.actions, np.float32).reshape(-1, 2)
    if actions is not None and (replayed.shape != actions.shape or not np.allclose(replayed, actions)):
        raise PlaysegError(f"episode {episode_id}: replaying its seed gives other commands than recorded")
    return recording.scenes, segments


def draw_task(
    scene: Scene, rng: np.random.Generator, exclude: Task | None = None, tasks: TaskSet = TASK_SETS["all"]
) -> Task | None:
    """A task of ``tasks`` that may be given in ``scene``, drawn as the set draws (`TaskSet.by_family`:
    a family uniformly, then one of its tasks; or one of the tasks uniformly), never ``exclude``; None if
    none."""
    by_family = applicable_tasks(scene, tasks.members)
    if exclude is not None and exclude.family in by_family:
        remaining = [task for task in by_family[exclude.family] if task != exclude]
        if remaining:
            by_family[exclude.family] = remaining
        else:
            del by_family[exclude.family]
    if not by_family:
        return None
    if not tasks.by_family:
        candidates = [task for family in sorted(by_family) for task in by_family[family]]
        return candidates[int(rng.integers(len(candidates)))]
    families = sorted(by_family)
    family_tasks = by_family[families[int(rng.integers(len(families)))]]
    return family_tasks[int(rng.integers(len(family_tasks)))]


def run_task(recorder: Recorder, teleop: Teleoperator, task: Task, max_steps: int) -> bool:
    """Let the teleoperator carry out ``task`` until the oracle says done (True) or ``max_steps`` pass."""
    start = recorder.scene
    teleop.begin(task, start)
    for _ in range(max_steps):
        scene = recorder.step(teleop.act(recorder.scene))
        if is_done(task, scene, start):
            return True
    return False


def play(
    config: PlayConfig, seed: int, recorder: Callable[[TabletopSim, Renderer], Recorder] = Recorder
) -> tuple[Recorder, list[Segment], PlayStats]:
    """Play one episode from ``seed`` into a recorder made by ``recorder(sim, renderer)``; returns it,
    the ground-truth segments and the teleoperator's record.

    Deterministic: same config and seed, same run (a recorder only reads the sim, never changes it).
    """
    rng = np.random.default_rng(seed)
    sim = TabletopSim()
    sim.place_randomly(rng)
    recording = recorder(sim, Renderer(config.image_size))
    teleop = Teleoperator(config.teleop, rng)
    stats = PlayStats()
    segments: list[Segment] = []
    wanted = int(rng.integers(config.tasks_per_episode[0], config.tasks_per_episode[1] + 1))
    failures, previous, tasks = 0, None, config.tasks
    while len(segments) < wanted and failures < config.max_failures:
        if rng.random() < config.idle_chance:
            teleop.begin_idle("pause" if rng.random() < 0.5 else "wander")
            steps = int(rng.integers(config.idle_steps[0], config.idle_steps[1] + 1))
            for _ in range(steps):
                recording.step(teleop.act(recording.scene))
            stats.idle_steps += steps
        task = draw_task(recording.scene, rng, exclude=previous, tasks=tasks)
        if task is None:
            break
        previous = task
        start = recording.steps
        solved = run_task(recording, teleop, task, config.max_task_steps)
        stats.count(task, solved)
        if solved:
            segments.append(Segment(start, recording.steps, task.text))
            stats.task_lengths.append(recording.steps - start)
            failures = 0
        else:
            stats.failed_steps += recording.steps - start
            failures += 1
    return recording, segments, stats


def generate_episode(config: PlayConfig, seed: int) -> PlayEpisode:
    """One deterministic play episode (same config and seed -> identical arrays and segments)."""
    recording, segments, stats = play(config, seed)
    episode = Episode(
        episode_id=episode_id_for_seed(seed),
        actions=np.asarray(recording.actions, dtype=np.float32).reshape(-1, 2),
        images={CAMERA: np.stack(recording.frames)},
        state=np.stack(recording.states),
        segments=segments,
    )
    return PlayEpisode(episode, stats)


__all__ = [
    "PlayConfig",
    "Recorder",
    "SceneRecorder",
    "PlayEpisode",
    "PlayStats",
    "draw_task",
    "episode_id_for_seed",
    "generate_episode",
    "play",
    "replay_scenes",
    "run_task",
    "seed_of_episode",
]

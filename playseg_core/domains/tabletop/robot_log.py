"""Tabletop play as a robot logs it: streams at their own rates with times, not steps.

A `RobotLog` is one play episode (the same run as `play.generate_episode` with the same seed) as a
real robot would record it: camera frames at the control rate, the effector's state as a joint-state
sensor at a higher rate (sampled between control steps from the physics itself, not interpolated),
commands at the control rate, and the instruction segments as time ranges. Times are integer
nanoseconds (ROS time). playseg_ros/tabletop writes it as a rosbag2 bag of standard messages; this
module knows nothing of ROS.

Step k's observation is taken at ``start_ns + k * period``; its command is sent at the same time and
acts until the next; a segment [s, e) is the time range [t_s, t_e] (its end is the observation where
the oracle said done).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Segment
from playseg_core.domains.tabletop.play import PlayConfig, PlayStats, Recorder, episode_id_for_seed, play
from playseg_core.domains.tabletop.render import Renderer
from playseg_core.domains.tabletop.sim import TabletopSim
from playseg_core.domains.tabletop.spec import CAMERA, CONTROL_HZ, DOMAIN, PHYSICS_SUBSTEPS
from playseg_core.errors import PlaysegError

JOINT_NAMES: tuple[str, str] = ("effector_x", "effector_y")
"""The effector's two prismatic axes as a joint-state sensor names them (position m, velocity m/s)."""

LOG_START_NS = 1_767_225_600 * 10**9
"""Default start of a log: a fixed UTC time (whole seconds), so a generated log is the same every run."""

DEFAULT_STATE_HZ = 50.0
"""The joint-state sensor's default rate (Hz)."""

NS = 10**9

EPISODE_GAP_NS = 5 * NS
"""The pause between two logs recorded one after the other (the operator resets the table)."""


def consecutive_starts_ns(num_steps: Sequence[int], first_ns: int = LOG_START_NS) -> list[int]:
    """The start of each of logs of ``num_steps`` control steps recorded one after the other, from
    ``first_ns``, ``EPISODE_GAP_NS`` apart: a robot's episodes follow one another in time."""
    starts, at = [], first_ns
    for steps in num_steps:
        starts.append(at)
        at += steps * round(NS / CONTROL_HZ) + EPISODE_GAP_NS
    return starts


@dataclass
class RobotLog:
    """One episode's streams. ``*_ns`` are the times (int64 ns) of the rows of the arrays beside them.

    frames (N, H, W, 3) uint8 RGB at ``camera_hz``; joint_positions, joint_velocities (M, 2) at
    ``state_hz``, named `JOINT_NAMES`; commands (N - 1, 2) planar velocity (m/s) at ``command_hz``;
    segments: the ground truth in steps, and `segment_times` the same as (start_ns, end_ns, instruction).
    """

    episode_id: str
    frame_ns: np.ndarray
    frames: np.ndarray
    joint_ns: np.ndarray
    joint_positions: np.ndarray
    joint_velocities: np.ndarray
    command_ns: np.ndarray
    commands: np.ndarray
    segments: list[Segment]
    stats: PlayStats
    joint_names: tuple[str, ...] = JOINT_NAMES
    camera_hz: float = CONTROL_HZ
    state_hz: float = CONTROL_HZ
    command_hz: float = CONTROL_HZ

    @property
    def segment_times(self) -> list[tuple[int, int, str]]:
        return [
            (int(self.frame_ns[s.start]), int(self.frame_ns[s.end]), s.instruction) for s in self.segments
        ]

    @property
    def end_ns(self) -> int:
        return int(max(self.frame_ns[-1], self.joint_ns[-1]))


class _SampledRecorder(Recorder):
    """A `Recorder` that also reads the effector's state every ``every`` physics substeps."""

    def __init__(self, sim: TabletopSim, renderer: Renderer, every: int) -> None:
        super().__init__(sim, renderer)
        self.every = every
        scene = self.scene
        self.samples: list[tuple[float, float, float, float]] = [(*scene.effector, *scene.effector_velocity)]

    def apply(self, action: np.ndarray) -> tuple[float, float]:
        command, samples = self.sim.step_sampled(action, self.every)
        self.samples.extend(samples)
        return command


def record_robot_log(
    config: PlayConfig, seed: int, state_hz: float = DEFAULT_STATE_HZ, start_ns: int = LOG_START_NS
) -> RobotLog:
    """The play episode of ``seed`` as a robot log, its joint states at ``state_hz`` (a multiple of the
    control rate that divides the physics rate: 10, 20, 50 or 100 Hz)."""
    per_step = state_hz / CONTROL_HZ
    if per_step != int(per_step) or per_step < 1 or PHYSICS_SUBSTEPS % int(per_step):
        raise PlaysegError(
            f"tabletop state rate {state_hz} Hz: must be a multiple of {CONTROL_HZ:g} Hz dividing "
            f"{CONTROL_HZ * PHYSICS_SUBSTEPS:g} Hz"
        )
    every = PHYSICS_SUBSTEPS // int(per_step)
    recording, segments, stats = play(
        config, seed, lambda sim, renderer: _SampledRecorder(sim, renderer, every)
    )
    assert isinstance(recording, _SampledRecorder)
    steps = len(recording.actions)
    step_ns = round(NS / CONTROL_HZ)
    sample_ns = round(NS / state_hz)
    samples = np.asarray(recording.samples, dtype=np.float64)
    return RobotLog(
        episode_id=episode_id_for_seed(seed),
        frame_ns=start_ns + step_ns * np.arange(steps + 1, dtype=np.int64),
        frames=np.stack(recording.frames),
        joint_ns=start_ns + sample_ns * np.arange(len(samples), dtype=np.int64),
        joint_positions=samples[:, :2],
        joint_velocities=samples[:, 2:],
        command_ns=start_ns + step_ns * np.arange(steps, dtype=np.int64),
        commands=np.asarray(recording.actions, dtype=np.float64).reshape(-1, 2),
        segments=segments,
        stats=stats,
        state_hz=float(state_hz),
    )


def dataset_play_config(dataset: PlayDataset) -> PlayConfig:
    """The `PlayConfig` a tabletop dataset was generated with (its ``meta.play_config``)."""
    if dataset.domain != DOMAIN:
        raise PlaysegError(f"{dataset.path}: a {dataset.domain!r} dataset, not {DOMAIN!r} play")
    raw = dataset.info.get("meta", {}).get("play_config")
    if raw is None:
        raise PlaysegError(
            f"{dataset.path}: meta/info.json has no meta.play_config (not generated by playseg)"
        )
    return PlayConfig.from_json(raw, f"{dataset.path}: meta.play_config")


def replay_dataset_episode(
    dataset: PlayDataset,
    index: int,
    config: PlayConfig | None = None,
    state_hz: float = DEFAULT_STATE_HZ,
    start_ns: int = LOG_START_NS,
) -> RobotLog:
    """Episode ``index`` of a generated tabletop dataset as a robot log: replayed from its seed (its
    ``meta/episodes.jsonl`` row) and checked against the dataset (frames, actions, states, segments), so
    the log holds exactly the dataset's episode; ValueError naming what differs otherwise."""
    config = dataset_play_config(dataset) if config is None else config
    record = dataset.records[index]
    where = f"{dataset.path}: episode {record.episode_id}"
    seed = record.extra.get("seed")
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise PlaysegError(f"{where}: meta/episodes.jsonl gives no integer extra.seed to replay it from")
    log = record_robot_log(config, seed, state_hz=state_hz, start_ns=start_ns)
    episode = dataset.episode(index, truth=True)
    every = round(state_hz / CONTROL_HZ)
    at_frames = np.concatenate([log.joint_positions, log.joint_velocities], axis=1)[::every]
    differences = [
        ("id", log.episode_id == episode.episode_id),
        ("actions", np.array_equal(log.commands.astype(np.float32), episode.actions)),
        ("frames", np.array_equal(log.frames, episode.images[CAMERA])),
        ("states", episode.state is not None and np.array_equal(at_frames.astype(np.float32), episode.state)),
        (
            "segments",
            [(s.start, s.end, s.instruction) for s in log.segments]
            == [(s.start, s.end, s.instruction) for s in episode.segments],
        ),
    ]
    wrong = [name for name, same in differences if not same]
    if wrong:
        raise PlaysegError(
            f"{where}: replaying seed {seed} does not give the dataset's {', '.join(wrong)} "
            "(generated by another version of the tabletop domain?)"
        )
    return log


__all__ = [
    "DEFAULT_STATE_HZ",
    "JOINT_NAMES",
    "EPISODE_GAP_NS",
    "LOG_START_NS",
    "RobotLog",
    "consecutive_starts_ns",
    "dataset_play_config",
    "record_robot_log",
    "replay_dataset_episode",
]

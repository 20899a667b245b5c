"""A generic robot for benchmarks and tests: an arm with no domain package, recorded in standard messages.

A five-joint arm with a gripper (sensor_msgs/JointState, 7 positions: five joints, two fingers), a camera
in front of it (sensor_msgs/Image rgb8: the arm and the props it works on) and the operator's
end-effector velocity command (geometry_msgs/Twist, header-less, as a space mouse publishes it), each at
its own rate. Its play is a chain of skills, each a joint-space motion through its own waypoints to its
own target (minimum-jerk phases, the gripper closing or opening where the skill ends with a grasp or a
release), never the same skill twice in a row, with idle pauses between some of them. The operator adds
noise everywhere: waypoints, speed, a hand tremor, noisy commands; the joint encoders and the camera add
their own. Ground truth: the skills' time ranges, on a 0.1 s grid (the frames an annotation tool shows),
in the sidecar format `playseg convert` reads (docs/convert.md "Annotations").

    play = Play(seed=3, seconds=60.0)
    write_robot_bag(Path("bags/run_03"), play, annotated=True)   # labels.yaml + ground_truth.yaml
    yaml.safe_dump(robot_mapping("robot0", fps=10))               # the `playseg convert` mapping

Nothing in playseg knows this robot: it is data, like a team's own bags.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

CAMERA_HZ, JOINT_HZ, COMMAND_HZ = 30, 100, 30
JOINT_NAMES = ("base_yaw", "shoulder", "elbow", "wrist_pitch", "wrist_roll", "finger_left", "finger_right")
ARM_JOINTS = 5
LINKS = (0.45, 0.40, 0.16)  # shoulder -> elbow -> wrist -> gripper tip, metres
BASE_HEIGHT = 0.25
LABEL_PERIOD = 0.1
"""Skill boundaries lie on this grid (seconds): an annotation tool shows frames at 10 Hz."""
LABELS_FILE, TRUTH_FILE = "labels.yaml", "ground_truth.yaml"
START_NS = 1_700_000_000 * 10**9


@dataclass(frozen=True)
class Skill:
    """A skill: its instruction, the arm's waypoints (five joints each; the last is the target) and what
    the gripper does at the end (None: it stays as it is)."""

    instruction: str
    waypoints: tuple[tuple[float, ...], ...]
    grip: float | None = None  # 0 open, 1 closed


SKILLS = (
    Skill("pick the block from the left bin", ((0.9, 0.55, -1.1, -1.0, 0.0), (0.9, 0.1, -0.8, -0.9, 0.0)), 1.0),
    Skill("place the block in the right bin", ((-0.9, 0.6, -1.1, -1.0, 0.0), (-0.9, 0.15, -0.85, -0.9, 0.0)), 0.0),
    Skill("press the button", ((0.35, 0.6, -1.4, -0.8, 0.0), (0.35, 0.25, -1.15, -0.9, 0.0))),
    Skill("open the drawer", ((-0.35, 0.2, -0.6, -1.0, 1.57), (-0.35, 0.5, -1.5, -0.6, 1.57))),
    Skill("go to the home pose", ((0.0, 1.2, -2.0, -0.6, 0.0),)),
    Skill("wave at the camera", ((0.0, 1.4, -0.4, 0.2, 0.0), (0.0, 1.4, -0.4, 0.2, 0.8), (0.0, 1.4, -0.4, 0.2, -0.8),
                                 (0.0, 1.4, -0.4, 0.2, 0.0))),
)  # fmt: skip
INSTRUCTIONS = tuple(skill.instruction for skill in SKILLS)
HOME_SKILL = SKILLS[4]
HOME = np.array(HOME_SKILL.waypoints[0])
GRIP_SECONDS = 0.4


@dataclass(frozen=True)
class Phase:
    """The arm moving from ``start`` to ``goal`` (minimum jerk) and the gripper from ``grip_from`` to
    ``grip_to`` over [t0, t1) seconds."""

    t0: float
    t1: float
    start: np.ndarray
    goal: np.ndarray
    grip_from: float
    grip_to: float


def _grid(seconds: float) -> float:
    return round(seconds / LABEL_PERIOD) * LABEL_PERIOD


def _min_jerk(s: float) -> float:
    return s**3 * (10 - 15 * s + 6 * s**2)


def forward_kinematics(q: np.ndarray) -> np.ndarray:
    """(4, 3) points in metres, x right, y away from the camera, z up: shoulder, elbow, wrist, tip."""
    yaw, angles = q[0], np.cumsum(q[1:4])
    radius = np.concatenate([[0.0], np.cumsum(np.array(LINKS) * np.cos(angles))])
    height = BASE_HEIGHT + np.concatenate([[0.0], np.cumsum(np.array(LINKS) * np.sin(angles))])
    return np.stack([radius * np.sin(yaw), radius * np.cos(yaw), height], axis=1)


class Play:
    """A robot's play as functions of time: the skills one after another, with pauses, from ``seed``.

    ``skills`` holds (start s, end s, skill index) of every skill that finishes within ``seconds``; the
    time after the last one is idle.
    """

    def __init__(self, seed: int, seconds: float, pause_share: float = 0.35) -> None:
        rng = np.random.default_rng(seed)
        self.seconds = seconds
        self.skills: list[tuple[float, float, int]] = []
        self.phases: list[Phase] = []
        q = HOME + rng.normal(0.0, 0.05, ARM_JOINTS)
        grip = 0.0
        t = _grid(float(rng.uniform(0.3, 1.0)))  # the operator takes the controls
        skill = SKILLS.index(HOME_SKILL)  # the arm starts at home: the first skill goes elsewhere
        while True:
            skill = int((skill + rng.integers(1, len(SKILLS))) % len(SKILLS))
            phases, q_end, grip_end = self._plan(SKILLS[skill], q, grip, t, rng)
            if phases[-1].t1 > seconds - 0.5:
                break
            self.phases += phases
            self.skills.append((t, phases[-1].t1, skill))
            q, grip, t = q_end, grip_end, phases[-1].t1
            if rng.random() < pause_share:
                t = t + _grid(float(rng.uniform(0.5, 2.5)))
        self.final = (q, grip)
        self.starts = np.array([phase.t0 for phase in self.phases])
        self.tremor_freq = rng.uniform(0.7, 3.0, (3, ARM_JOINTS))
        self.tremor_phase = rng.uniform(0.0, 2 * np.pi, (3, ARM_JOINTS))
        self.tremor_amp = 0.006

    @staticmethod
    def _plan(
        skill: Skill, q: np.ndarray, grip: float, t0: float, rng: np.random.Generator
    ) -> tuple[list[Phase], np.ndarray, float]:
        """The phases of one skill from pose ``q``; its length is stretched onto the label grid."""
        speed = float(rng.uniform(0.75, 1.35))  # this operator's pace for this skill
        goals = [np.array(w) + rng.normal(0.0, 0.04, ARM_JOINTS) for w in skill.waypoints]
        durations = [
            (0.45 + 0.8 * float(np.max(np.abs(b - a)))) * speed
            for a, b in zip([q] + goals[:-1], goals, strict=True)
        ]
        gripping = skill.grip is not None and skill.grip != grip
        if gripping:
            durations.append(GRIP_SECONDS * speed)
        total = sum(durations)
        scale = max(_grid(total), 2 * LABEL_PERIOD) / total
        phases, start, t = [], q, t0
        for goal, seconds in zip(goals, durations, strict=False):
            phases.append(Phase(t, t + seconds * scale, start, goal, grip, grip))
            start, t = goal, t + seconds * scale
        grip_to = skill.grip if gripping else grip
        if gripping:
            phases.append(Phase(t, t + durations[-1] * scale, start, start, grip, grip_to))
        last = phases[-1]
        phases[-1] = Phase(
            last.t0, t0 + _grid(total * scale), last.start, last.goal, last.grip_from, last.grip_to
        )
        return phases, start, float(grip_to)

    def at(self, t: float) -> tuple[int, float]:
        """The skill at time ``t`` (-1 when idle) and how far it has come (0..1)."""
        for start, end, skill in self.skills:
            if start <= t < end:
                return skill, (t - start) / (end - start)
        return -1, 0.0

    def pose(self, t: float) -> tuple[np.ndarray, float]:
        """The arm's five joints (tremor included) and the gripper (0 open .. 1 closed) at ``t``."""
        index = int(np.searchsorted(self.starts, t, side="right")) - 1
        if not self.phases:
            q, grip = self.final
        elif index < 0:
            q, grip = self.phases[0].start, self.phases[0].grip_from
        else:
            phase = self.phases[index]
            if t >= phase.t1:  # idle after this phase
                q, grip = phase.goal, phase.grip_to
            else:
                s = _min_jerk((t - phase.t0) / (phase.t1 - phase.t0))
                q = phase.start + s * (phase.goal - phase.start)
                grip = phase.grip_from + s * (phase.grip_to - phase.grip_from)
        tremor = self.tremor_amp * np.sin(2 * np.pi * self.tremor_freq * t + self.tremor_phase).sum(axis=0)
        return q + tremor, grip

    def joints(self, t: float) -> np.ndarray:
        """The seven JointState positions: five joints and two fingers (metres from closed)."""
        q, grip = self.pose(t)
        finger = 0.04 * (1.0 - grip)
        return np.concatenate([q, [finger, finger]])

    def command(self, t: float) -> tuple[float, float, float, float, float]:
        """The operator's Twist at ``t``: the gripper tip's velocity a little ahead (the arm follows the
        command) as linear x, y, z, the wrist's roll and the base's yaw rate as angular x, z."""
        lead, dt = 0.06, 0.02
        q0, _ = self.pose(t + lead - dt)
        q1, _ = self.pose(t + lead)
        velocity = (forward_kinematics(q1)[-1] - forward_kinematics(q0)[-1]) / dt
        return (*velocity.tolist(), (q1[4] - q0[4]) / dt, (q1[0] - q0[0]) / dt)

    def labels(self, offset: float = 0.0) -> list[dict]:
        """The skills as sidecar entries, in seconds from a bag's start ``offset`` seconds before t = 0."""
        return [
            {"start": round(offset + a, 9), "end": round(offset + b, 9), "instruction": SKILLS[k].instruction}
            for a, b, k in self.skills
        ]


# --- the camera ------------------------------------------------------------------------------------------

PROP_COLOURS = (
    (200, 60, 40),
    (40, 90, 210),
    (220, 30, 30),
    (150, 110, 60),
)  # left bin, right bin, button, drawer


def _project(points: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixel (column, row) of world points seen by the camera in front of the arm, a little above it."""
    scale = 0.55 * height
    col = width / 2 + scale * points[..., 0]
    row = height * 0.92 - scale * (points[..., 2] + 0.35 * points[..., 1])
    return np.stack([col, row], axis=-1)


def _box(frame: np.ndarray, centre: np.ndarray, half: tuple[int, int], colour) -> None:
    col, row = int(round(centre[0])), int(round(centre[1]))
    frame[
        max(0, row - half[1]) : max(0, row + half[1] + 1), max(0, col - half[0]) : max(0, col + half[0] + 1)
    ] = colour


class Camera:
    """Renders the arm and its props; ``width`` x ``height`` rgb8."""

    def __init__(self, width: int = 64, height: int = 48) -> None:
        self.width, self.height = width, height
        scene = np.zeros((height, width, 3), np.uint8)
        scene[:] = (175, 180, 190)  # wall
        table = _project(np.array([0.0, 0.0, 0.0]), width, height)[1]
        scene[int(table) :] = (120, 100, 80)
        for colour, skill in zip(PROP_COLOURS, SKILLS[:4], strict=True):
            tip = forward_kinematics(np.array(skill.waypoints[-1]))[-1]
            _box(scene, _project(tip - [0.0, 0.0, 0.05], width, height), (max(1, width // 24), 1), colour)
        self.scene = scene

    def image(self, q: np.ndarray, grip: float) -> np.ndarray:
        frame = self.scene.copy()
        points = _project(forward_kinematics(q), self.width, self.height)
        base = _project(np.array([0.0, 0.0, 0.0]), self.width, self.height)
        chain = np.concatenate([base[None], points])
        for link, (a, b) in enumerate(zip(chain[:-1], chain[1:], strict=True)):
            for s in np.linspace(0.0, 1.0, 1 + int(np.abs(b - a).max())):
                _box(frame, a + s * (b - a), (1, 1) if link < 2 else (0, 0), (60, 60, 70))
        spread = 1 + int(round(2 * (1.0 - grip)))
        tip = points[-1]
        for side in (-1, 1):
            _box(frame, tip + [side * spread, 1], (0, 1), (240, 200, 40))
        return frame


# --- the bag --------------------------------------------------------------------------------------------


def robot_mapping(robot: str = "robot0", fps: float = 10, annotations: str | None = LABELS_FILE) -> dict:
    """The `playseg convert` mapping of a bag of this robot: the camera as the primary, the joints
    nearest to each frame, the command in effect ('previous'); labels from the sidecar ``annotations``."""
    mapping = {
        "fps": fps,
        "primary": "observation.images.front",
        "tolerance_ms": 20,
        "features": {
            "observation.images.front": {"topic": f"/{robot}/camera/image_raw"},
            "observation.state": {"topic": f"/{robot}/joint_states", "field": "position"},
            "action": {
                "topic": f"/{robot}/cmd_vel",
                "fields": ["linear.x", "linear.y", "linear.z", "angular.x", "angular.z"],
                "align": "previous",
                "tolerance_ms": 50,
            },
        },
    }
    if annotations is not None:
        mapping["annotations"] = {"file": annotations}
    return mapping


def write_robot_bag(
    bag: Path,
    play: Play,
    robot: str = "robot0",
    annotated: bool = True,
    camera: Camera | None = None,
    seed: int = 0,
) -> None:
    """``play`` as ``robot`` records it (rosbags, MCAP): the camera at 30 Hz, the joints at 100 Hz and the
    command at 30 Hz on their own clocks; the ground truth in ``ground_truth.yaml``, and in
    ``labels.yaml`` too when ``annotated``."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from playseg_ros.convert.source import convert_typestore

    camera = camera or Camera()
    rng = np.random.default_rng(seed)
    store = convert_typestore()
    types = store.types
    Time, Header = types["builtin_interfaces/msg/Time"], types["std_msgs/msg/Header"]
    Vector3 = types["geometry_msgs/msg/Vector3"]

    def stamp(t_ns: int):
        return Time(sec=(START_NS + t_ns) // 10**9, nanosec=(START_NS + t_ns) % 10**9)

    # (time ns, topic, play time): frames exactly periodic from 0 (a triggered camera: the label grid's
    # frames); the joints and commands on their own phases with jitter, from a little before the first
    # frame to a little after the last (the first and last steps have their inputs)
    seconds = play.seconds
    events = [(k * 10**9 // CAMERA_HZ, "camera", k / CAMERA_HZ) for k in range(int(seconds * CAMERA_HZ))]
    for topic, hz, phase in (("joints", JOINT_HZ, -0.02), ("cmd", COMMAND_HZ, -0.5 / COMMAND_HZ)):
        for k in range(int((seconds + 0.1 - phase) * hz)):
            t = phase + k / hz + float(rng.uniform(-0.001, 0.001))
            events.append((int(round(t * 1e9)), topic, t))
    events.sort(key=lambda event: event[0])
    first_ns = events[0][0]  # the bag's start: label times count from it
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {
            "camera": writer.add_connection(f"/{robot}/camera/image_raw", "sensor_msgs/msg/Image", typestore=store),
            "joints": writer.add_connection(f"/{robot}/joint_states", "sensor_msgs/msg/JointState", typestore=store),
            "cmd": writer.add_connection(f"/{robot}/cmd_vel", "geometry_msgs/msg/Twist", typestore=store),
        }  # fmt: skip
        for t_ns, topic, t in events:
            if topic == "camera":
                q, grip = play.pose(t)
                frame = camera.image(q, grip).astype(np.int16) + rng.integers(
                    -3, 4, (camera.height, camera.width, 3)
                )
                message = types["sensor_msgs/msg/Image"](
                    header=Header(stamp=stamp(t_ns), frame_id="camera"), height=camera.height, width=camera.width,
                    encoding="rgb8", is_bigendian=0, step=camera.width * 3,
                    data=np.clip(frame, 0, 255).astype(np.uint8).reshape(-1),
                )  # fmt: skip
                kind = "sensor_msgs/msg/Image"
            elif topic == "joints":
                message = types["sensor_msgs/msg/JointState"](
                    header=Header(stamp=stamp(t_ns), frame_id=""), name=list(JOINT_NAMES),
                    position=play.joints(t) + rng.normal(0.0, 0.002, len(JOINT_NAMES)),
                    velocity=np.zeros(0), effort=np.zeros(0),
                )  # fmt: skip
                kind = "sensor_msgs/msg/JointState"
            else:
                vx, vy, vz, roll, yaw = np.array(play.command(t)) + rng.normal(0.0, 0.01, 5)
                message = types["geometry_msgs/msg/Twist"](
                    linear=Vector3(x=vx, y=vy, z=vz), angular=Vector3(x=roll, y=0.0, z=yaw)
                )
                kind = "geometry_msgs/msg/Twist"
            writer.write(connections[topic], START_NS + t_ns, store.serialize_cdr(message, kind))
    truth = yaml.safe_dump({"annotations": play.labels(-first_ns / 1e9)}, sort_keys=False)
    (bag / TRUTH_FILE).write_text(truth)
    if annotated:
        (bag / LABELS_FILE).write_text(truth)


def write_fleet(
    root: Path, bags: int, seconds: float, annotated: int, seed: int = 0, camera: Camera | None = None
) -> list[Path]:
    """``bags`` bags of ``seconds`` each under ``root`` (run_000, ...), ``annotated`` of them spread
    evenly with their skills as labels (labels.yaml), each with its ground truth; the two mappings next
    to them: ``map.yaml`` (the labels) and ``map_truth.yaml`` (the ground truth, for scoring)."""
    camera = camera or Camera()
    paths = []
    for number in range(bags):
        path = root / "bags" / f"run_{number:03d}"
        write_robot_bag(
            path, Play(seed * 100_000 + number, seconds), annotated=number * annotated % bags < annotated,
            camera=camera, seed=seed * 100_000 + number,
        )  # fmt: skip
        paths.append(path)
    (root / "map.yaml").write_text(yaml.safe_dump(robot_mapping(), sort_keys=False))
    (root / "map_truth.yaml").write_text(
        yaml.safe_dump(robot_mapping(annotations=TRUTH_FILE), sort_keys=False)
    )
    return paths


def pipeline(root: Path) -> list[list[str]]:
    """The CLI commands, with their defaults, from the bags under ``root`` (``write_fleet``) to the
    metrics on the unannotated bags: convert every bag, train PS, segment the unannotated play, convert
    the bags again with their ground truth, evaluate."""
    r = str(root)
    return [
        ["convert", f"{r}/bags", "--out", f"{r}/data", "--mapping", f"{r}/map.yaml"],
        ["train", "--data", f"{r}/data", "--out", f"{r}/ps.pt"],
        [
            "segment",
            "--model",
            f"{r}/ps.pt",
            "--input",
            f"{r}/data",
            "--splits",
            "play",
            "--out",
            f"{r}/segmented",
        ],
        ["convert", f"{r}/bags", "--out", f"{r}/truth", "--mapping", f"{r}/map_truth.yaml"],
        ["evaluate", "--pred", f"{r}/segmented", "--truth", f"{r}/truth"],
    ]

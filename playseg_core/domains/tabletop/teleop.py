"""A scripted teleoperator: plans and executes pushes the way a person with a joystick would.

For a block task it picks the block to move and a goal point for it, comes round to the far side of the
block (``approach``), then pushes it towards the goal while steering to stay behind it (``push``); when
the block slides off the line it comes round again. Per task it draws its own speeds, approach angle,
responsiveness and goal point inside the target region; every step adds hand jitter (an
Ornstein-Uhlenbeck process), and it sometimes hesitates before starting and pauses briefly mid-task.
So no two demonstrations of one instruction are alike.

It never decides completion: the task oracle (instructions.py) does, and the caller stops it then.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from playseg_core.domains.tabletop.instructions import (
    DIRECTIONS,
    NEXT_TO_GAP,
    PUSH_DISTANCE,
    SEPARATED_GAP,
    Task,
    region_box,
)
from playseg_core.domains.tabletop.sim import Scene
from playseg_core.domains.tabletop.spec import (
    BLOCK_EXTENTS,
    EFFECTOR_RADIUS,
    EFFECTOR_REACH,
    MAX_SPEED,
    TABLE_SIZE,
)
from playseg_core.errors import PlaysegError

CONTACT_MARGIN = 0.003
"""The effector aims this far behind the block's back face when pushing (m)."""
APPROACH_OFFSET = 0.02
"""Where the push starts: this much further behind the block than contact (m)."""
DETOUR_CLEARANCE = 0.025
"""A detour round the block passes this far outside contact distance (m)."""
GOAL_INSET = 0.015
"""Goal points lie this far inside a target region (m), so the block ends well inside it."""
TABLE_INSET = 0.012
"""A block's goal keeps it this far from the rims (m)."""
GOAL_TOLERANCE = 0.008
"""A block this close to its goal point is there (m)."""
STUCK_STEPS = 6
STUCK_DISTANCE = 0.004
"""Moving less than this (m) over STUCK_STEPS steps while meaning to move is being stuck."""
PLAN_CANDIDATES = 6
"""Goal points the operator considers for one push."""
MIN_CLEARANCE = 0.01
"""A push path is clear when it passes at least this far from every other block (m)."""


@dataclass(frozen=True)
class TeleopConfig:
    """The operator's habits; per task a value is drawn uniformly from each (low, high) range.

    approach_speed, push_speed: m/s. approach_angle: the largest angle (rad) between the line the operator
    comes in on and the push line. steering: gain (1/s) pulling the effector back behind the block.
    responsiveness: share of the gap between the current and the intended command closed per step
    (a hand's inertia). jitter: standard deviation (m/s) of the hand's noise. hesitation_chance: chance
    to wait hesitation_steps before starting a task; pause_chance: per step, chance of a pause of
    pause_steps.
    """

    approach_speed: tuple[float, float] = (0.09, 0.18)
    push_speed: tuple[float, float] = (0.06, 0.14)
    approach_angle: float = 0.35
    steering: tuple[float, float] = (2.0, 4.0)
    responsiveness: tuple[float, float] = (0.45, 0.85)
    jitter: float = 0.01
    hesitation_chance: float = 0.4
    hesitation_steps: tuple[int, int] = (1, 5)
    pause_chance: float = 0.015
    pause_steps: tuple[int, int] = (1, 4)

    def __post_init__(self) -> None:
        for name in ("approach_speed", "push_speed", "steering", "responsiveness"):
            low, high = getattr(self, name)
            if not 0.0 < low <= high:
                raise PlaysegError(f"TeleopConfig.{name} must be a range 0 < low <= high, got {(low, high)}")
        if self.responsiveness[1] > 1.0 or max(self.approach_speed[1], self.push_speed[1]) > MAX_SPEED:
            raise PlaysegError("TeleopConfig: responsiveness must be <= 1 and speeds <= MAX_SPEED")
        for name in ("hesitation_chance", "pause_chance"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise PlaysegError(f"TeleopConfig.{name} must be in [0, 1], got {getattr(self, name)}")


Vec = tuple[float, float]


def _unit(vector: np.ndarray) -> np.ndarray:
    norm = math.hypot(vector[0], vector[1])
    return vector / norm if norm > 1e-9 else np.array([1.0, 0.0])


def _unit_xy(x: float, y: float) -> Vec:
    norm = math.hypot(x, y)
    return (x / norm, y / norm) if norm > 1e-9 else (1.0, 0.0)


def _rotate(vector: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * vector[0] - s * vector[1], s * vector[0] + c * vector[1]])


def _segment_point_distance(a: Vec, b: Vec, point: Vec) -> float:
    """Distance from ``point`` to the segment from ``a`` to ``b``."""
    abx, aby = b[0] - a[0], b[1] - a[1]
    length2 = abx * abx + aby * aby
    t = 0.0
    if length2 > 1e-12:
        t = min(1.0, max(0.0, ((point[0] - a[0]) * abx + (point[1] - a[1]) * aby) / length2))
    return math.hypot(point[0] - a[0] - t * abx, point[1] - a[1] - t * aby)


def _path_clearance(scene: Scene, block: int, goal: np.ndarray, exclude: int = -1) -> float:
    """How far ``block``, pushed straight to ``goal``, passes from the nearest other block (gap, m)."""
    a = scene.points[block]
    b = (float(goal[0]), float(goal[1]))
    clearance = math.inf
    for other, centre in enumerate(scene.points):
        if other in (block, exclude):
            continue
        distance = _segment_point_distance(a, b, (centre[0], centre[1]))
        clearance = min(clearance, distance - BLOCK_EXTENTS[block] - BLOCK_EXTENTS[other])
    return clearance


def _reach(position: Vec, target: Vec, speed: float) -> Vec:
    """Towards ``target`` at ``speed``, slowing down over the last few centimetres."""
    dx, dy = target[0] - position[0], target[1] - position[1]
    distance = math.hypot(dx, dy)
    if distance < 1e-6:
        return (0.0, 0.0)
    scale = min(speed, 2.5 * distance) / distance
    return (dx * scale, dy * scale)


def _clip_to_table(point: np.ndarray, inset: float) -> np.ndarray:
    return np.clip(point, inset, TABLE_SIZE - inset)


def _clip_to_reach(point: Vec) -> Vec:
    low, high = -EFFECTOR_REACH + 0.002, TABLE_SIZE + EFFECTOR_REACH - 0.002
    return (min(high, max(low, point[0])), min(high, max(low, point[1])))


class Teleoperator:
    """Drives the effector through one task (`begin`, then `act` every step) or an idle stretch
    (`begin_idle`). Draws all its variation from ``rng``."""

    def __init__(self, config: TeleopConfig, rng: np.random.Generator) -> None:
        self.config = config
        self.rng = rng
        self.command: Vec = (0.0, 0.0)
        self._noise: Vec = (0.0, 0.0)
        self._task: Task | None = None
        self._idle_kind = ""
        self._heading: Vec = (1.0, 0.0)
        self._mover = -1
        self._goal = np.zeros(2)
        self._mode = "approach"
        self._wait = 0
        self._side = 1.0
        self._bearing = 0.0
        self._trail: list[Vec] = []
        self._escape: Vec = (0.0, 0.0)
        self._escape_steps = 0
        self._stuck = 0
        # This demonstration's style (drawn anew by `begin` and `begin_idle`).
        self._approach_speed = config.approach_speed[0]
        self._push_speed = config.push_speed[0]
        self._angle = 0.0
        self._steering = config.steering[0]
        self._responsiveness = config.responsiveness[1]

    def _draw(self, bounds: tuple[float, float]) -> float:
        return float(self.rng.uniform(*bounds))

    # ------------------------------------------------------------------ starting a task

    def begin(self, task: Task, scene: Scene) -> None:
        """Start ``task`` in ``scene``: draw this demonstration's style and fix its goal."""
        cfg = self.config
        self._task = task
        self._idle_kind = ""
        self._approach_speed = self._draw(cfg.approach_speed)
        self._push_speed = self._draw(cfg.push_speed)
        self._angle = self._draw((-cfg.approach_angle, cfg.approach_angle))
        self._steering = self._draw(cfg.steering)
        self._responsiveness = self._draw(cfg.responsiveness)
        self._side = 1.0 if self.rng.random() < 0.5 else -1.0
        self._mode = "approach"
        low, high = cfg.hesitation_steps
        self._wait = int(self.rng.integers(low, high + 1)) if self.rng.random() < cfg.hesitation_chance else 0
        self._mover, self._goal = self._plan(task, scene)
        self._trail.clear()
        self._escape_steps = 0
        self._stuck = 0

    def _plan(self, task: Task, scene: Scene) -> tuple[int, np.ndarray]:
        """The block to move (-1: the effector itself) and where to.

        Like an operator, it looks for a goal point with a clear way there: among a few candidates (in
        random order) the first whose straight push path misses the other blocks, else the clearest.
        For next-to the goal is a side (bearing) of the other block, and follows that block as it moves.
        """
        if task.family == "effector_to_region":
            return -1, self._point_in_region(task.region, 0.01)
        if task.family == "separate_blocks":
            return self._separation(scene, task.block, task.other)
        block = task.block
        inset = BLOCK_EXTENTS[block] + TABLE_INSET
        candidates: list[np.ndarray] = []
        if task.family == "block_to_region":
            candidates = [
                _clip_to_table(self._point_in_region(task.region, GOAL_INSET), inset)
                for _ in range(PLAN_CANDIDATES)
            ]
        elif task.family == "block_in_direction":
            direction = np.array(DIRECTIONS[task.direction])
            sideways = np.array([-direction[1], direction[0]])
            candidates = [
                _clip_to_table(
                    scene.blocks[block]
                    + direction * (PUSH_DISTANCE + self._draw((0.02, 0.05)))
                    + sideways * self._draw((-0.03, 0.03)),
                    inset,
                )
                for _ in range(PLAN_CANDIDATES)
            ]
        elif task.family == "block_next_to_block":
            towards = scene.blocks[block] - scene.blocks[task.other]
            here = math.atan2(towards[1], towards[0])
            offsets = [self._draw((-0.2, 0.2)) + k for k in (0.0, 0.5, -0.5, 1.0, -1.0, 1.4, -1.4)]
            bearings = [here + offset for offset in offsets]
            # Only sides of the other block where the mover fits on the table and that it can reach
            # without going round the other block.
            bearings = [b for b in bearings if self._next_to_fits(scene, block, task.other, b)] or bearings
            candidates = [self._next_to_goal(scene, block, task.other, bearing) for bearing in bearings]
            best = self._clearest(scene, block, candidates, exclude=task.other)
            self._bearing = bearings[best]
            return block, candidates[best]
        else:
            raise PlaysegError(f"tabletop teleoperator: no plan for family {task.family!r}")
        return block, candidates[self._clearest(scene, block, candidates)]

    def _clearest(self, scene: Scene, block: int, goals: list[np.ndarray], exclude: int = -1) -> int:
        """Index of the first goal with a clear push (path and the effector's place behind the block
        free of other blocks), else of the one with the most clearance."""
        scores = []
        for goal in goals:
            clearance = _path_clearance(scene, block, goal, exclude)
            push = _unit(goal - scene.blocks[block])
            if clearance >= MIN_CLEARANCE and self._behind_is_free(scene, block, push):
                return len(scores)
            scores.append(clearance)
        return int(np.argmax(scores))

    def _point_in_region(self, region: str, inset: float) -> np.ndarray:
        x0, y0, x1, y1 = region_box(region)
        return np.array([self._draw((x0 + inset, x1 - inset)), self._draw((y0 + inset, y1 - inset))])

    @staticmethod
    def _next_to_fits(scene: Scene, block: int, other: int, bearing: float) -> bool:
        distance = BLOCK_EXTENTS[block] + BLOCK_EXTENTS[other] + 0.4 * NEXT_TO_GAP
        side = np.array([math.cos(bearing), math.sin(bearing)])
        goal = scene.blocks[other] + distance * side
        inset = BLOCK_EXTENTS[block] + TABLE_INSET
        on_table = bool(np.all(goal >= inset) and np.all(goal <= TABLE_SIZE - inset))
        return on_table and float((scene.blocks[block] - goal) @ side) >= 0.0

    @staticmethod
    def _next_to_goal(scene: Scene, block: int, other: int, bearing: float) -> np.ndarray:
        """The point at ``bearing`` from ``other`` where ``block`` would lie next to it."""
        distance = BLOCK_EXTENTS[block] + BLOCK_EXTENTS[other] + 0.4 * NEXT_TO_GAP
        goal = scene.blocks[other] + distance * np.array([math.cos(bearing), math.sin(bearing)])
        return _clip_to_table(goal, BLOCK_EXTENTS[block] + TABLE_INSET)

    def _separation(self, scene: Scene, a: int, b: int) -> tuple[int, np.ndarray]:
        """Which of two touching blocks to push, and where: sideways-away from the other (straight away
        would need the effector between them), wherever there is room."""
        movers = [a, b] if self.rng.random() < 0.5 else [b, a]
        angles = [math.radians(v) for v in (60, -60, 80, -80, 40, -40, 100, -100)]
        distance = self._draw((0.11, 0.15))
        options: list[tuple[int, np.ndarray]] = []
        for mover in movers:
            other = b if mover == a else a
            away = _unit(scene.blocks[mover] - scene.blocks[other])
            inset = BLOCK_EXTENTS[mover] + TABLE_INSET
            for angle in angles:
                goal = _clip_to_table(scene.blocks[mover] + _rotate(away, angle) * distance, inset)
                gap = math.hypot(*(goal - scene.blocks[other])) - BLOCK_EXTENTS[mover] - BLOCK_EXTENTS[other]
                if gap >= SEPARATED_GAP + 0.02:
                    options.append((mover, goal))
        if not options:  # hemmed in: push the first mover sideways anyway
            mover, other = movers[0], b if movers[0] == a else a
            away = _unit(scene.blocks[mover] - scene.blocks[other])
            goal = scene.blocks[mover] + _rotate(away, angles[0]) * distance
            return mover, _clip_to_table(goal, BLOCK_EXTENTS[mover] + TABLE_INSET)
        scores = []
        for mover, goal in options:
            clearance = _path_clearance(scene, mover, goal, exclude=-1)
            if clearance >= MIN_CLEARANCE and self._behind_is_free(
                scene, mover, _unit(goal - scene.blocks[mover])
            ):
                return mover, goal
            scores.append(clearance)
        return options[int(np.argmax(scores))]

    @staticmethod
    def _behind_is_free(scene: Scene, block: int, direction: np.ndarray) -> bool:
        """Whether the effector fits behind ``block`` to push it along ``direction``."""
        behind = scene.blocks[block] - direction * (BLOCK_EXTENTS[block] + EFFECTOR_RADIUS + CONTACT_MARGIN)
        for other, centre in enumerate(scene.blocks):
            if other != block and math.hypot(*(behind - centre)) < BLOCK_EXTENTS[other] + EFFECTOR_RADIUS:
                return False
        return True

    def begin_idle(self, kind: str) -> None:
        """Start an unlabelled stretch: ``"pause"`` (the hand rests on the stick) or ``"wander"``
        (aimless moves)."""
        if kind not in ("pause", "wander"):
            raise PlaysegError(f"tabletop teleoperator: unknown idle kind {kind!r} (pause, wander)")
        self._task = None
        self._idle_kind = kind
        self._responsiveness = self._draw(self.config.responsiveness)
        bearing = self._draw((-math.pi, math.pi))
        self._heading = (math.cos(bearing), math.sin(bearing))
        self._approach_speed = self._draw(self.config.approach_speed)

    # ------------------------------------------------------------------ acting
    # Plain float arithmetic from here on: this runs every step, where numpy's per-call cost dominates.

    def act(self, scene: Scene) -> np.ndarray:
        """The velocity command for this step (m/s, within the action bounds)."""
        cfg = self.config
        effector = scene.effector_point
        if self._task is None:
            intended = self._idle_intent(effector)
        elif self._wait > 0:
            self._wait -= 1
            intended = (0.0, 0.0)
        elif cfg.pause_chance and self.rng.random() < cfg.pause_chance:
            low, high = cfg.pause_steps
            self._wait = int(self.rng.integers(low, high + 1)) - 1
            intended = (0.0, 0.0)
        elif self._escape_steps > 0:
            self._escape_steps -= 1
            intended = self._escape
        elif self._mover < 0:
            intended = self._travel(scene, effector, (float(self._goal[0]), float(self._goal[1])), -1)
        else:
            intended = self._push_intent(scene, effector)
        self._watch_progress(scene, effector, intended)
        # Hand jitter: an Ornstein-Uhlenbeck process, correlated over a few steps.
        kick = self.rng.normal(0.0, cfg.jitter * math.sqrt(1 - 0.49), size=2).tolist()
        nx, ny = self._noise
        self._noise = (0.7 * nx + kick[0], 0.7 * ny + kick[1])
        cx, cy = self.command
        share = self._responsiveness
        self.command = (cx + share * (intended[0] - cx), cy + share * (intended[1] - cy))
        return np.array(
            [
                min(MAX_SPEED, max(-MAX_SPEED, self.command[0] + self._noise[0])),
                min(MAX_SPEED, max(-MAX_SPEED, self.command[1] + self._noise[1])),
            ]
        )

    def _push_intent(self, scene: Scene, effector: Vec) -> Vec:
        mover = self._mover
        bx, by = scene.points[mover]
        ex, ey = effector
        if self._task is not None and self._task.family == "block_next_to_block":
            gx, gy = self._next_to_goal(scene, mover, self._task.other, self._bearing).tolist()
        else:
            gx, gy = float(self._goal[0]), float(self._goal[1])
        if math.hypot(gx - bx, gy - by) < GOAL_TOLERANCE and self._task is not None:
            # The block is where it was meant to go, yet the task is not done (another block moved
            # too, say): the operator looks again and makes a new plan from here.
            self._mover, self._goal = self._plan(self._task, scene)
            self._mode = "approach"
            return (0.0, 0.0)
        px, py = _unit_xy(gx - bx, gy - by)
        extent = BLOCK_EXTENTS[mover]
        contact = extent + EFFECTOR_RADIUS + CONTACT_MARGIN
        behind = (bx - px * contact, by - py * contact)
        rx, ry = ex - bx, ey - by
        along = rx * px + ry * py
        lateral = px * ry - py * rx
        if self._mode == "push":
            lost = (
                abs(lateral) > 0.8 * extent
                or along > -extent
                or math.hypot(ex - behind[0], ey - behind[1]) > 0.03
            )
            if not lost:
                return self._push_velocity((px, py), behind, effector)
            self._mode = "approach"
            self._angle *= 0.5  # coming round again, the operator lines up more carefully
        c, s = math.cos(self._angle), math.sin(self._angle)
        reach = contact + APPROACH_OFFSET
        start = _clip_to_reach((bx - (c * px - s * py) * reach, by - (s * px + c * py) * reach))
        if math.hypot(ex - start[0], ey - start[1]) < 0.01:
            self._mode = "push"
            return self._push_velocity((px, py), behind, effector)
        return self._travel(scene, effector, start, mover)

    def _travel(self, scene: Scene, effector: Vec, target: Vec, mover: int) -> Vec:
        """Towards ``target``, round the first block in the way (the mover included); a block lying on
        the target itself is shoved aside rather than circled for ever."""
        blocker, nearest = -1, math.inf
        for index, (x, y) in enumerate(scene.points):
            room = BLOCK_EXTENTS[index] + EFFECTOR_RADIUS + (0.005 if index == mover else 0.003)
            occupied = index != mover and math.hypot(x - target[0], y - target[1]) < room + 0.01
            if not occupied and _segment_point_distance(effector, target, (x, y)) < room:
                distance = math.hypot(x - effector[0], y - effector[1])
                if distance < nearest:
                    blocker, nearest = index, distance
        if blocker >= 0:
            centre = scene.points[blocker]
            contact = BLOCK_EXTENTS[blocker] + EFFECTOR_RADIUS + CONTACT_MARGIN
            target = self._detour(effector, centre, target, contact)
        return _reach(effector, target, self._approach_speed)

    def _watch_progress(self, scene: Scene, effector: Vec, intended: Vec) -> None:
        """Stuck (meaning to move, hardly moving: hemmed in by blocks against a rim)? Back away for a few
        steps, away from the nearest block and a little sideways, then try the other way round."""
        self._trail.append(effector)
        if len(self._trail) > STUCK_STEPS:
            self._trail.pop(0)
        wants_to_move = math.hypot(intended[0], intended[1]) > 0.03
        if not wants_to_move or len(self._trail) < STUCK_STEPS:
            return
        first, last = self._trail[0], self._trail[-1]
        if math.hypot(last[0] - first[0], last[1] - first[1]) > STUCK_DISTANCE:
            return
        distances = [math.hypot(x - effector[0], y - effector[1]) for x, y in scene.points]
        nearest = scene.points[int(np.argmin(distances))]
        away = _unit_xy(effector[0] - float(nearest[0]), effector[1] - float(nearest[1]))
        turn = self._draw((-0.8, 0.8))
        c, s = math.cos(turn), math.sin(turn)
        speed = self._approach_speed
        self._escape = ((c * away[0] - s * away[1]) * speed, (s * away[0] + c * away[1]) * speed)
        self._escape_steps = int(self.rng.integers(3, 7))
        self._side = -self._side
        self._trail.clear()
        self._stuck += 1
        if self._stuck % 2 == 0 and self._task is not None:
            # Stuck again: this way does not work; think again from here (another goal, another block).
            self._mover, self._goal = self._plan(self._task, scene)
            self._mode = "approach"

    def _push_velocity(self, push: Vec, behind: Vec, effector: Vec) -> Vec:
        """Along the push line, steering back to the point just behind the block."""
        k = self._steering
        vx = push[0] * self._push_speed + k * (behind[0] - effector[0])
        vy = push[1] * self._push_speed + k * (behind[1] - effector[1])
        largest = max(abs(vx), abs(vy))
        scale = MAX_SPEED / largest if largest > MAX_SPEED else 1.0
        return (vx * scale, vy * scale)

    def _detour(self, effector: Vec, block: Vec, start: Vec, contact: float) -> Vec:
        """The straight way to ``start`` would hit the block: circle round it, a quarter turn ahead of
        the effector's bearing on the way to the start point's bearing."""
        here = math.atan2(effector[1] - block[1], effector[0] - block[0])
        there = math.atan2(start[1] - block[1], start[0] - block[0])
        turn = (there - here + math.pi) % (2 * math.pi) - math.pi
        if abs(abs(turn) - math.pi) < 0.3:  # straight across: keep the side chosen for this task
            turn = self._side * abs(turn)
        bearing = here + math.copysign(min(abs(turn), math.pi / 4), turn)
        radius = contact + DETOUR_CLEARANCE
        return _clip_to_reach((block[0] + radius * math.cos(bearing), block[1] + radius * math.sin(bearing)))

    def _idle_intent(self, effector: Vec) -> Vec:
        if self._idle_kind == "pause":
            return (0.0, 0.0)
        # Wander: a slowly turning heading, bent back towards the table's middle near the edges.
        turn = self._draw((-0.4, 0.4))
        hx, hy = self._heading
        hx, hy = hx * math.cos(turn) - hy * math.sin(turn), hx * math.sin(turn) + hy * math.cos(turn)
        middle = TABLE_SIZE / 2
        if max(abs(effector[0] - middle), abs(effector[1] - middle)) > middle - 0.06:
            cx, cy = _unit_xy(middle - effector[0], middle - effector[1])
            hx, hy = _unit_xy(0.5 * hx + cx, 0.5 * hy + cy)
        self._heading = (hx, hy)
        speed = 0.6 * self._approach_speed
        return (hx * speed, hy * speed)


__all__ = ["TeleopConfig", "Teleoperator"]

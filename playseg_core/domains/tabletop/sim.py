"""The tabletop physics: a pymunk world with a table, rims, 8 blocks and a round end effector.

Top-down, so there is no gravity; table friction is Coulomb friction per block (a pivot and a gear joint
to the table with a bounded force and torque, pymunk's usual top-down friction), so a block slides only
while it is pushed. The effector is a heavy disc driven by a velocity servo (a pivot joint with a bounded
force to an invisible kinematic "hand" that moves at the commanded velocity): it pushes blocks, but a
block pinned against a rim stops it instead of being crushed through it. It passes over the rims (they
stop only blocks). The hand's velocity follows the command with a first-order lag sampled at the
control rate: each step it moves ``1 - exp(-dt / EFFECTOR_TIME_CONSTANT)`` of the way to the command.
The state's velocity is the effector's measured velocity.

pymunk is deterministic for the same sequence of calls, so a sim driven by the same seed and actions
reproduces its states bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import pymunk

from playseg_core.domains.tabletop.spec import (
    BLOCK_EXTENTS,
    BLOCK_FRICTION,
    BLOCK_MASS,
    BLOCKS,
    CONTROL_HZ,
    CUBE_SIDE,
    CYLINDER_RADIUS,
    EFFECTOR_RADIUS,
    EFFECTOR_REACH,
    EFFECTOR_TIME_CONSTANT,
    MAX_SPEED,
    PHYSICS_SUBSTEPS,
    TABLE_SIZE,
)
from playseg_core.errors import PlaysegError

GRAVITY = 9.81
PHYSICS_DT = 1.0 / (CONTROL_HZ * PHYSICS_SUBSTEPS)
RIM_THICKNESS = 0.02
EFFECTOR_LOW = -EFFECTOR_REACH
EFFECTOR_HIGH = TABLE_SIZE + EFFECTOR_REACH

EFFECTOR_MASS = 1.0  # kg
EFFECTOR_MAX_FORCE = 20.0
"""The servo's force bound (N): enough to push a row of blocks, not to crush one into a rim."""
RIMS = pymunk.ShapeFilter(categories=0b10)
EFFECTOR_FILTER = pymunk.ShapeFilter(mask=pymunk.ShapeFilter.ALL_MASKS() ^ 0b10)
"""The effector collides with the blocks, not with the rims."""

SLEEP_SPEED = 0.002
SLEEP_AFTER = 0.2
"""A block slower than SLEEP_SPEED (m/s) for SLEEP_AFTER seconds stops and sleeps until touched."""

PLACEMENT_MARGIN = 0.06
"""Blocks are placed at least this far from the table's edge (m)."""
PLACEMENT_MIN_DISTANCE = 0.09
"""Centres of randomly placed blocks are at least this far apart (m)."""


@dataclass(frozen=True)
class Scene:
    """A snapshot of the table: what the task oracle and the teleoperator read.

    blocks: (8, 2) block centres; angles: (8,) block orientations; effector, effector_velocity: (2,).
    """

    blocks: np.ndarray
    angles: np.ndarray
    effector: np.ndarray
    effector_velocity: np.ndarray

    @cached_property
    def points(self) -> list[tuple[float, float]]:
        """The block centres as Python floats (what per-step geometry reads; numpy scalars are slow)."""
        return [(x, y) for x, y in self.blocks.tolist()]

    @cached_property
    def effector_point(self) -> tuple[float, float]:
        x, y = self.effector.tolist()
        return (x, y)


def physics_stepper(space: pymunk.Space) -> Callable[[float], None]:
    """``space.step`` without its per-call bookkeeping (bodies added or removed during a step, post-step
    callbacks: this world uses neither), which costs more than the physics itself for 9 bodies (~2.5 of
    ~5 us per substep). Falls back to ``space.step`` if pymunk's internals are not as expected."""
    try:
        from pymunk._chipmunk import lib

        handle = space._space
        step = lib.cpSpaceStep
    except (ImportError, AttributeError):
        return space.step

    def raw_step(dt: float) -> None:
        step(handle, dt)

    return raw_step


def _clip_command(action: np.ndarray | tuple[float, float]) -> tuple[float, float]:
    """The command as applied: clipped to the bounds, rounded to float32 (as datasets store actions, so
    replaying recorded actions reproduces the recorded run exactly)."""
    if len(action) != 2:
        raise PlaysegError(f"tabletop action {action!r}: expected 2 velocities (x, y)")
    vx, vy = float(action[0]), float(action[1])
    if not (math.isfinite(vx) and math.isfinite(vy)):
        raise PlaysegError(f"tabletop action {action!r}: velocities must be finite numbers")
    clipped = np.array([min(MAX_SPEED, max(-MAX_SPEED, vx)), min(MAX_SPEED, max(-MAX_SPEED, vy))], np.float32)
    return (float(clipped[0]), float(clipped[1]))


class TabletopSim:
    """One table. `place` or `place_randomly` sets it up; `step` applies one control step."""

    def __init__(self) -> None:
        space = pymunk.Space()
        space.gravity = (0.0, 0.0)
        space.iterations = 10
        space.collision_slop = 0.0005  # pymunk's default (0.1) assumes pixels, not metres
        # Blocks at rest sleep (cost nothing) until something touches them: most of the table is still
        # most of the time, and this makes the physics ~3x faster.
        space.idle_speed_threshold = SLEEP_SPEED
        space.sleep_time_threshold = SLEEP_AFTER
        self.space = space
        self._add_rims()
        self.blocks: list[pymunk.Body] = [self._add_block(index) for index in range(len(BLOCKS))]
        self.effector = pymunk.Body(EFFECTOR_MASS, math.inf)  # does not turn
        effector_shape = pymunk.Circle(self.effector, EFFECTOR_RADIUS)
        effector_shape.friction = 0.3
        effector_shape.filter = EFFECTOR_FILTER
        self._hand = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        servo = pymunk.PivotJoint(self._hand, self.effector, (0.0, 0.0), (0.0, 0.0))
        servo.max_bias = 0.0  # matches velocities only: where the hand is does not matter
        servo.max_force = EFFECTOR_MAX_FORCE
        space.add(self.effector, effector_shape, self._hand, servo)
        self._physics_step = physics_stepper(space)
        self._velocity = (0.0, 0.0)
        self._response = 1.0 - math.exp(-1.0 / (CONTROL_HZ * EFFECTOR_TIME_CONSTANT))

    def _add_rims(self) -> None:
        # Thick segments just outside the edges: their inner surface is the table's edge.
        low, high, r = -RIM_THICKNESS, TABLE_SIZE + RIM_THICKNESS, RIM_THICKNESS
        corners = [(low, low), (high, low), (high, high), (low, high)]
        for a, b in zip(corners, corners[1:] + corners[:1], strict=True):
            rim = pymunk.Segment(self.space.static_body, a, b, r)
            rim.friction = 0.3
            rim.filter = RIMS
            self.space.add(rim)

    def _add_block(self, index: int) -> pymunk.Body:
        if BLOCKS[index].endswith("cube"):
            body = pymunk.Body(BLOCK_MASS, pymunk.moment_for_box(BLOCK_MASS, (CUBE_SIDE, CUBE_SIDE)))
            shape: pymunk.Shape = pymunk.Poly.create_box(body, (CUBE_SIDE, CUBE_SIDE))
        else:
            body = pymunk.Body(BLOCK_MASS, pymunk.moment_for_circle(BLOCK_MASS, 0.0, CYLINDER_RADIUS))
            shape = pymunk.Circle(body, CYLINDER_RADIUS)
        shape.friction = 0.4
        shape.elasticity = 0.0
        self.space.add(body, shape)
        table = self.space.static_body
        sliding = pymunk.PivotJoint(table, body, (0.0, 0.0), (0.0, 0.0))
        sliding.max_bias = 0.0  # no position correction: the joint only resists motion
        sliding.max_force = BLOCK_FRICTION * BLOCK_MASS * GRAVITY
        turning = pymunk.GearJoint(table, body, 0.0, 1.0)
        turning.max_bias = 0.0
        turning.max_force = BLOCK_FRICTION * BLOCK_MASS * GRAVITY * BLOCK_EXTENTS[index] * 0.5
        self.space.add(sliding, turning)
        return body

    def place(
        self,
        blocks: np.ndarray | list[tuple[float, float]],
        effector: tuple[float, float] | np.ndarray,
        angles: np.ndarray | list[float] | None = None,
    ) -> None:
        """Put the blocks (8 centres) and the effector at rest where given; ValueError if off the table."""
        blocks = np.asarray(blocks, dtype=np.float64)
        if blocks.shape != (len(BLOCKS), 2):
            raise PlaysegError(
                f"tabletop blocks must be {len(BLOCKS)} (x, y) centres, got shape {blocks.shape}"
            )
        if np.any(blocks < 0.0) or np.any(blocks > TABLE_SIZE):
            raise PlaysegError(f"tabletop blocks must lie on the table [0, {TABLE_SIZE}]^2")
        ex, ey = float(effector[0]), float(effector[1])
        if not (EFFECTOR_LOW <= ex <= EFFECTOR_HIGH and EFFECTOR_LOW <= ey <= EFFECTOR_HIGH):
            raise PlaysegError(f"tabletop effector ({ex}, {ey}) outside [{EFFECTOR_LOW}, {EFFECTOR_HIGH}]^2")
        angles = np.zeros(len(BLOCKS)) if angles is None else np.asarray(angles, dtype=np.float64)
        for body, (x, y), angle in zip(self.blocks, blocks, angles, strict=True):
            body.position = (float(x), float(y))
            body.angle = float(angle)
            body.velocity = (0.0, 0.0)
            body.angular_velocity = 0.0
            body.activate()
        for body in (self.effector, self._hand):
            body.position = (ex, ey)
            body.velocity = (0.0, 0.0)
        self._velocity = (0.0, 0.0)
        self.space.reindex_shapes_for_body(self.effector)
        for body in self.blocks:
            self.space.reindex_shapes_for_body(body)

    def place_randomly(self, rng: np.random.Generator) -> None:
        """A random layout: blocks apart from each other and from the edges, the effector anywhere."""
        low, high = PLACEMENT_MARGIN, TABLE_SIZE - PLACEMENT_MARGIN
        centres: list[np.ndarray] = []
        while len(centres) < len(BLOCKS):
            candidate = rng.uniform(low, high, size=2)
            if all(np.hypot(*(candidate - c)) >= PLACEMENT_MIN_DISTANCE for c in centres):
                centres.append(candidate)
            elif len(centres) and rng.random() < 0.01:
                centres = []  # a crowded start: begin again rather than search forever
        angles = rng.uniform(-math.pi / 4, math.pi / 4, size=len(BLOCKS))
        effector = rng.uniform(0.05, TABLE_SIZE - 0.05, size=2)
        self.place(np.array(centres), effector, angles)

    def step(self, action: np.ndarray | tuple[float, float]) -> tuple[float, float]:
        """Command the effector's planar velocity for one control step (1 / CONTROL_HZ s).

        The command is clipped to [-MAX_SPEED, MAX_SPEED] per axis (returned as applied); the effector
        stops at the edge of its reach [-EFFECTOR_REACH, TABLE_SIZE + EFFECTOR_REACH]^2 (braking within
        ~2 mm of it).
        """
        command = _clip_command(action)
        self._command(command)
        step, dt = self._physics_step, PHYSICS_DT
        for _ in range(PHYSICS_SUBSTEPS):
            step(dt)
        return command

    def step_sampled(
        self, action: np.ndarray | tuple[float, float], every: int
    ) -> tuple[tuple[float, float], list[tuple[float, float, float, float]]]:
        """`step`, also reading the effector's state (x, y, velocity x, velocity y) after every ``every``
        physics substeps: a state sensor faster than the control rate. Same physics as `step`."""
        if every < 1 or PHYSICS_SUBSTEPS % every:
            raise PlaysegError(
                f"tabletop state sampling: every must divide {PHYSICS_SUBSTEPS} substeps, got {every}"
            )
        command = _clip_command(action)
        self._command(command)
        step, dt, effector = self._physics_step, PHYSICS_DT, self.effector
        samples = []
        for substep in range(1, PHYSICS_SUBSTEPS + 1):
            step(dt)
            if substep % every == 0:
                (x, y), (vx, vy) = effector.position, effector.velocity
                samples.append((x, y, vx, vy))
        return command, samples

    def _command(self, command: tuple[float, float]) -> None:
        """Set the hand's velocity for the coming control step (lagged command, kept within reach)."""
        vx, vy = self._velocity
        vx += (command[0] - vx) * self._response
        vy += (command[1] - vy) * self._response
        x, y = self.effector.position
        # Stop at the edge of the reach: never step past it.
        horizon = 1.0 / CONTROL_HZ
        vx = min(max(vx, (EFFECTOR_LOW - x) / horizon), (EFFECTOR_HIGH - x) / horizon)
        vy = min(max(vy, (EFFECTOR_LOW - y) / horizon), (EFFECTOR_HIGH - y) / horizon)
        self._hand.velocity = (vx, vy)
        self.effector.activate()  # the hand moves it: it must never sleep
        self._velocity = (vx, vy)

    def scene(self) -> Scene:
        """The current positions and velocities (copies)."""
        blocks = self.blocks
        return Scene(
            blocks=np.array([body.position for body in blocks]),
            angles=np.array([body.angle for body in blocks]),
            effector=np.array(self.effector.position),
            effector_velocity=np.array(self.effector.velocity),
        )

    def state_vector(self) -> np.ndarray:
        """The proprioceptive state (spec.STATE_NAMES): effector x, y, velocity x, velocity y, float32."""
        x, y = self.effector.position
        vx, vy = self.effector.velocity
        return np.array((x, y, vx, vy), dtype=np.float32)


__all__ = ["PHYSICS_DT", "Scene", "TabletopSim"]

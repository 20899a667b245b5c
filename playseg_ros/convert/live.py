"""The mapping live: topic messages in, PlaySteps (and step-numbered annotations) out, through the same
`StepBuilder` as `playseg convert` (stepping.py). No ROS graph here: nodes/topic_adapter.py feeds it.

A *stream* is what `playseg convert` calls a bag: messages until the input falls silent for the node's
``idle_timeout_s`` (or the node is deactivated). Its episodes are numbered as a bag's are
(``<episode_id>:<k>``, k counting on over streams), step by step as the builder decides them. Message
times follow the mapping's ``clock`` as in a bag: ``header`` takes ``header.stamp`` when set; a message
without one (and ``clock: receive``) takes the time the adapter received it: the node's clock, right on a
robot. In a replay (the player publishing the recording's time on /clock, the adapter with
``use_sim_time``) `ReplayStamps` gives such a message the /clock value in effect when it was *published*,
which is its recorded time: the steps are then those `playseg convert` makes of the bag, however late the
adapter takes the message.

Memory stays bounded when one mapped topic falls silent (a camera dies) while the others go on: a topic
``max_lag_s`` behind the newest sample of the others is reported silent and no longer waited for
(stepping.py); steps without its sample are dropped as convert drops them on the recorded bag.

Human labels: ``playseg_msgs/TimedAnnotation`` messages on the mapping's annotation topic are turned into
step ranges of the episode holding them (annotations.py, as convert does) when that episode ends.
"""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from playseg_core.data.episode import Segment
from playseg_core.data.features import STATE
from playseg_core.errors import PlaysegError
from playseg_ros.convert.annotations import TimedLabel, check_label_type, label_of, segments_of_episodes
from playseg_ros.convert.errors import ConvertError
from playseg_ros.convert.mapping import ConvertMapping
from playseg_ros.convert.source import message_time
from playseg_ros.convert.stepping import BuiltStep, StepBuilder

DEFAULT_MAX_LAG_S = 10.0
"""How far a topic may lag behind the newest sample before it counts as silent: far above what DDS
delivery of topics on one graph lags (milliseconds), well below what buffering a camera for long costs
(10 s of 30 Hz 640x480 rgb8 is 280 MB)."""


@dataclass
class LiveStep:
    """One PlayStep's content: observation ``step`` of episode ``episode_id``."""

    episode_id: str
    step: int
    time_ns: int
    frames: dict[str, np.ndarray]  # camera feature name -> (H, W, 3) uint8, in the mapping's order
    state: np.ndarray | None
    action: np.ndarray | None  # None on the episode's last step (episode_end)


@dataclass
class LiveOutput:
    steps: list[LiveStep] = field(default_factory=list)
    annotations: list[tuple[str, Segment]] = field(default_factory=list)  # (episode id, segment)
    notes: list[str] = field(default_factory=list)


class LiveMapping:
    """Feed it messages (`add`), collect what is decided; `end_stream` when the input fell silent."""

    def __init__(
        self,
        mapping: ConvertMapping,
        episode_id: str,
        source: str = "live",
        max_lag_s: float = DEFAULT_MAX_LAG_S,
        first_episode: int = 0,
    ) -> None:
        if not max_lag_s > 0:
            raise PlaysegError(f"max_lag_s must be > 0, got {max_lag_s}")
        self.mapping, self.prefix, self.source = mapping, episode_id, source
        self.max_lag_ns = round(max_lag_s * 1e9)
        self.episodes_done = first_episode  # episodes of earlier streams (and earlier mappings of a node)
        self.steps_published = 0
        self._new_stream()

    def _new_stream(self) -> None:
        self.builder = StepBuilder(self.mapping, self.source, drop_bad=True, max_lag_ns=self.max_lag_ns)
        self.labels: list[TimedLabel] = []
        self._open_times: list[int] = []  # step times of the episode being handed out
        self._notes_seen = 0
        self._silences_seen = 0
        self._outliers_seen = 0
        self._episodes_started = 0  # episodes of this stream with a step handed out

    @property
    def topics(self) -> list[str]:
        return self.mapping.topics

    def add(self, topic: str, msgtype: str, msg: Any, received_ns: int) -> LiveOutput:
        """One message; what it decided."""
        out = LiveOutput()
        if topic == self.mapping.annotation_topic:
            try:
                check_label_type(self.source, topic, msgtype)
                self.labels.append(label_of(msg))
            except ConvertError as error:  # reported; the stream goes on without this label
                out.notes.append(str(error))
        if topic in self.builder.buffers or topic == self.mapping.marker_topic:
            stamp = message_time(msg, received_ns, self.mapping.clock == "header")
            try:
                self.builder.add(topic, stamp, msg, msgtype)
                self._collect(self.builder.take(), out)
            except ConvertError as error:  # a bad topic (e.g. not an image): reported, the stream goes on
                out.notes.append(str(error))
            self.builder.prune()
        self._new_notes(out)
        return out

    def end_stream(self) -> LiveOutput:
        """The input fell silent: decide the rest, end the last episode; the next message starts anew."""
        out = LiveOutput()
        try:
            self._collect(self.builder.finish(), out)
        except ConvertError as error:
            out.notes.append(str(error))
        self._new_notes(out)
        out.notes += [f"stream ended: {note}" for note in self.drop_notes()]
        # every episode with a step out counts, also one the builder could not finish: its id is never
        # published again from step 0
        self.episodes_done += max(self.builder.episodes_kept, self._episodes_started)
        self._new_stream()
        return out

    def _collect(self, built: list[BuiltStep], out: LiveOutput) -> None:
        for step in built:
            episode_id = f"{self.prefix}:{self.episodes_done + step.episode}"
            self._episodes_started = max(self._episodes_started, step.episode + 1)
            frames = {name: step.observation[name] for name, f in self.mapping.features.items() if f.is_image}
            state = step.observation.get(STATE)
            out.steps.append(LiveStep(episode_id, step.step, step.time_ns, frames, state, step.action))
            self.steps_published += 1
            self._open_times.append(step.time_ns)
            if step.last:
                self._label_episode(episode_id, out)

    def _label_episode(self, episode_id: str, out: LiveOutput) -> None:
        times = np.asarray(self._open_times, dtype=np.int64)
        self._open_times = []
        if not self.labels:
            return
        (segments,), notes = segments_of_episodes([times], self.labels)
        out.annotations += [(episode_id, segment) for segment in segments]
        # a label of no step of this episode may belong to a later one (kept below, not reported yet); one
        # that ended before this episode began arrived after its own episode closed: reported
        late = [label for label in self.labels if label.end_ns <= times[0]]
        out.notes += [f"episode {episode_id!r}: {note}" for note in notes if "no step of any" not in note]
        out.notes += [
            f"label {label.instruction!r} [{label.start_ns}, {label.end_ns}] ns arrived after its episode "
            "closed: not applied"
            for label in late
        ]
        # a label starting in this episode belongs to it (cut at its end, as convert does); later ones wait
        self.labels = [label for label in self.labels if label.start_ns > times[-1]]

    def _new_notes(self, out: LiveOutput) -> None:
        bad, silences, outliers = self.builder.bad, self.builder.silences, self.builder.outliers
        out.notes += bad[self._notes_seen :] + silences[self._silences_seen :]
        out.notes += outliers[self._outliers_seen :]  # each stamp outlier warned about once
        self._notes_seen, self._silences_seen, self._outliers_seen = len(bad), len(silences), len(outliers)

    def drop_notes(self) -> list[str]:
        """The stream's drop counts so far (per feature, primary gaps, short episodes)."""
        return [n for n in self.builder.notes() if n not in self.builder.bad]


REPLAY_CLOCK_HISTORY = 20_000
"""/clock values kept to stamp messages taken late (a bag player publishes one per message: minutes)."""

REPLAY_HELD_MAX = 1_000
"""Messages held for a later /clock at most; past it (the /clock publisher stopped) the oldest is stamped
with the newest clock known, reported."""


class ReplayStamps:
    """Times of messages without a header in a replay: the /clock value in effect when each was published.

    A player publishing the recording's time on /clock before each message (bag_player ``clock``; rosbag2
    publishes /clock at a fixed rate instead, up to one period early) makes that value the message's recorded time. Publication order is read from
    DDS source timestamps (the publishing process's wall clock, the same for the player's /clock and its
    messages), so the time does not depend on when the adapter takes the message or the /clock. A message
    is held until a /clock published after it arrives (the clocks before it have then arrived too: one
    writer delivers in order) or the stream ends; one published before any /clock (the replay's time not
    set yet) has no recorded time and is refused.

    ``clock`` and ``stamp`` return the (time, item) pairs they released, in the order of their items."""

    def __init__(self, history: int = REPLAY_CLOCK_HISTORY, held_max: int = REPLAY_HELD_MAX) -> None:
        self._sources: deque[int] = deque(maxlen=history)  # /clock source timestamps, ascending
        self._times: deque[int] = deque(maxlen=history)  # their /clock values
        self._held: deque[tuple[int, Any]] = deque()  # (source timestamp, item) waiting for a later /clock
        self.held_max = held_max
        self.refused = 0  # items published before any /clock
        self.last_refused: Any = None
        self.forced = 0  # items stamped without a later /clock (held_max exceeded)

    @property
    def started(self) -> bool:
        return bool(self._times)

    def clock(self, source_ns: int, time_ns: int) -> list[tuple[int, Any]]:
        """A /clock message: its source timestamp and value."""
        if self._sources and source_ns < self._sources[-1]:  # the wall clock stepped back: start over
            self._sources.clear()
            self._times.clear()
        self._sources.append(source_ns)
        self._times.append(time_ns)
        released = []
        while self._held and self._held[0][0] < source_ns:
            released += self._release(*self._held.popleft())
        return released

    def stamp(self, source_ns: int, item: Any) -> list[tuple[int, Any]]:
        """A message without a time of its own: released now, or held for a later /clock."""
        if self._sources and source_ns < self._sources[-1]:
            return self._release(source_ns, item)
        self._held.append((source_ns, item))
        released = []
        while len(self._held) > self.held_max:
            self.forced += 1
            released += self._release(*self._held.popleft())
        return released

    def flush(self) -> list[tuple[int, Any]]:
        """The stream ended: every held message, stamped with the /clock before it."""
        released = []
        while self._held:
            released += self._release(*self._held.popleft())
        return released

    def _release(self, source_ns: int, item: Any) -> list[tuple[int, Any]]:
        i = bisect.bisect_right(self._sources, source_ns) - 1
        if i < 0:
            self.refused += 1
            self.last_refused = item
            return []
        return [(self._times[i], item)]

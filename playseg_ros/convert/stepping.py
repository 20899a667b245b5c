"""The steps of a mapping built from topic samples, one step at a time: the ONE implementation of the
step clock, alignment, decoding, drops, episodes and actions, shared by `playseg convert` (build.py adds a
whole bag's samples, then calls `finish`) and the live adapter node (nodes/topic_adapter.py adds
messages as they arrive and takes the steps decided so far).

The rules (docs/convert.md, "Alignment"):

- Step clock: the primary's samples are thinned to the mapping's fps (a sample is taken when at least
  one period, less half the primary's typical interval, has passed since the last one taken). The
  typical interval is the median of the primary's first `TYPICAL_INTERVALS` intervals (live, the clock
  starts once that many have arrived). A gap longer than a period and a half counts the steps it should
  have held as dropped (unless it ends an episode with ``split: gap``).
- A step at time t is **decided** once every feature's topic has a sample later than t + that feature's
  tolerance (no sample within the tolerance can still come, given a topic arrives in time order), or
  the input has ended. Each feature is then aligned (alignment.py) and decoded (decode.py); a step where
  any feature has no sample within its tolerance is dropped, never filled in.
- Episodes: a kept step starts a new episode after a pause longer than ``gap_s`` since the previous kept
  step (``split: gap``), or when a marker lies in (previous kept step, this step] (``split: marker``).
  An episode with fewer than ``min_steps`` actions is dropped whole.
- Actions: step k's action is the action feature aligned at step k, or derived from step k+1's
  observation (``derive``); the last observation of an episode has none. So a step is handed out once
  the next kept step of its episode is known (or the episode ended), and not before its episode has
  ``min_steps`` actions (a short episode is never half published).
- Live only (``max_lag_ns``): a topic whose newest sample is more than ``max_lag_ns`` behind the newest
  sample of any mapped topic is *silent* (a camera died). Steps older than that horizon are decided
  with what has arrived, so a feature of the silent topic without a sample within its tolerance drops
  its step as convert drops it on the recorded bag, and samples older than the horizon (less the
  tolerance) are forgotten: memory stays bounded while a topic is silent. A sample arriving later than
  the horizon cannot change a step any more; the bound must exceed the largest lag the input can have.
- Stamp outliers (`StampFilter`, live and offline alike, over each topic's samples in arrival order: a
  bag's recording order): a sample stamped more than a *jump* (``OUTLIER_INTERVALS`` typical intervals
  of its topic, at least two step periods) away from the topic's previous sample is held until the
  topic's next sample. When that one lies nearer the previous sample than the held one, the held one was
  a single bad stamp (a clock glitch a year ahead or behind, a stale frame) and is dropped, with a note
  naming topic and stamp; otherwise time really jumped (a pause) and it is kept. A topic's first sample
  is kept once a second one agrees with it (or a third says which of the two is out of line); a suspect
  with no sample after it is dropped. So one bad stamp costs one sample, never the stream: unfiltered, a
  stamp a year ahead moved the step clock, the newest time and so every topic's horizon a year on.
"""

from __future__ import annotations

import bisect
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from playseg_core.data.features import ACTION, Feature, Features
from playseg_core.errors import PlaysegError
from playseg_ros.convert.alignment import Alignment, align
from playseg_ros.convert.decode import IMAGE_TYPES, DecodeError, NumericDecoder, decode_image
from playseg_ros.convert.errors import ConvertError
from playseg_ros.convert.mapping import ConvertMapping, DerivedAction, TopicFeature

TYPICAL_INTERVALS = 16
"""The primary's typical interval is the median of this many of its first intervals."""

OUTLIER_INTERVALS = 4
"""A sample further than this many typical intervals of its topic from the previous one is a suspect."""

OUTLIER_NOTES = 10
"""Outliers of one topic reported one by one (live warnings); further ones are only counted."""


@dataclass
class BuiltStep:
    """One observation of an episode, with the action taken after it (None on the episode's last)."""

    episode: int  # index among the episodes kept so far (0, 1, ...)
    step: int  # index within its episode
    time_ns: int
    observation: dict[str, np.ndarray]  # feature name -> row (cameras (H, W, 3) uint8, state float32)
    action: np.ndarray | None
    last: bool


@dataclass
class TopicBuffer:
    """One topic's samples in time order (equal times keep their arrival order)."""

    msgtype: str = ""
    stamps: list[int] = field(default_factory=list)
    messages: list[Any] = field(default_factory=list)
    latest: int | None = None  # the latest time seen (pruning never lowers it)
    _array: np.ndarray | None = None

    def add(self, stamp: int, msg: Any) -> None:
        index = bisect.bisect_right(self.stamps, stamp)
        self.stamps.insert(index, stamp)
        self.messages.insert(index, msg)
        self.latest = stamp if self.latest is None else max(self.latest, stamp)
        self._array = None

    @property
    def array(self) -> np.ndarray:
        if self._array is None:
            self._array = np.asarray(self.stamps, dtype=np.int64)
        return self._array

    def prune(self, before_ns: int) -> None:
        """Forget samples older than ``before_ns`` (no undecided step can match them)."""
        cut = bisect.bisect_left(self.stamps, before_ns)
        if cut:
            del self.stamps[:cut], self.messages[:cut]
            self._array = None


class FeatureReader:
    """One feature's row at a step: the aligned sample(s) of its topic, decoded. Remembers the schema
    (image size; the numeric decoder made from the topic's first message)."""

    def __init__(self, feature: TopicFeature, source: Path | str) -> None:
        self.feature, self.source = feature, source
        self.decoder: NumericDecoder | None = None
        self.image_shape: tuple[int, ...] | None = None

    def match(self, step_ns: int, buffer: TopicBuffer) -> Alignment:
        return align(np.array([step_ns]), buffer.array, self.feature.align, self.feature.tolerance_ns)

    def decode(self, alignment: Alignment, buffer: TopicBuffer) -> np.ndarray:
        lo, hi = int(alignment.lo[0]), int(alignment.hi[0])
        if self.feature.is_image:
            return self._image(buffer, lo)
        if self.decoder is None:  # sizes, joint order and names from the topic's first message
            self.decoder = self._decoded(buffer, 0, lambda m: NumericDecoder.of_first(
                m, buffer.msgtype, self.feature.fields, self.feature.joints))  # fmt: skip
        pair = np.stack([self._decoded(buffer, i, self.decoder.decode) for i in (lo, hi)])
        # the same arithmetic as Alignment.take over a whole topic: row 0 is lo, row 1 is hi
        single = Alignment(np.array([0]), np.array([1]), alignment.weight, alignment.matched)
        return single.take(pair)[0]

    def _image(self, buffer: TopicBuffer, i: int) -> np.ndarray:
        if buffer.msgtype not in IMAGE_TYPES:
            raise ConvertError(
                self.source, f"type {buffer.msgtype} is not an image ({' or '.join(IMAGE_TYPES)})", self.topic
            )
        image = self._decoded(buffer, i, lambda m: decode_image(m, buffer.msgtype, self.feature.resize))
        if self.image_shape is None:
            self.image_shape = image.shape
        elif image.shape != self.image_shape:
            h, w = self.image_shape[:2]
            raise ConvertError(
                self.source,
                f"image of {image.shape[1]}x{image.shape[0]}, earlier ones {w}x{h} "
                "(resize to one size: 'resize')",
                self.topic,
                time_ns=buffer.stamps[i],
            )
        return image

    @property
    def topic(self) -> str:
        return self.feature.topic

    def _decoded(self, buffer: TopicBuffer, i: int, decode: Callable[[Any], Any]) -> Any:
        try:
            return decode(buffer.messages[i])
        except DecodeError as error:
            raise ConvertError(self.source, str(error), self.topic, error.field, buffer.stamps[i]) from None

    def schema(self) -> Feature:
        feature = self.feature
        if feature.is_image:
            shape = self.image_shape or (*(feature.resize[::-1] if feature.resize else (0, 0)), 3)
            return Feature(feature.name, "image", "uint8", tuple(shape))
        if self.decoder is None:
            raise ConvertError(self.source, "no messages", self.topic)
        size = self.decoder.size
        for bound, key in ((feature.low, "low"), (feature.high, "high")):
            if bound is not None and len(bound) != size:
                raise ConvertError(
                    self.source, f"mapping gives {len(bound)} {key} bounds for {size} values", self.topic
                )
        kind = "action" if feature.name == ACTION else "state"
        return Feature(
            feature.name, kind, "float32", (size,), self.decoder.names, low=feature.low, high=feature.high
        )


class StepClock:
    """The primary's samples taken as steps (the rule in the module docstring), one sample at a time."""

    def __init__(self, period_ns: int, typical_ns: int, episode_gap_ns: int | None) -> None:
        self.period, self.episode_gap = period_ns, episode_gap_ns
        self.slack = min(typical_ns // 2, period_ns // 2)
        self.last: int | None = None
        self.missing = 0
        self.first_gap: int | None = None

    def offer(self, stamp: int) -> bool:
        if self.last is None:
            self.last = stamp
            return True
        since = stamp - self.last
        if since < self.period - self.slack:
            return False
        long_gap = since > self.period + self.period // 2
        if long_gap and (self.episode_gap is None or since <= self.episode_gap):
            self.missing += round(since / self.period) - 1
            self.first_gap = self.first_gap if self.first_gap is not None else self.last
        self.last = stamp
        return True


class StampFilter:
    """One topic's samples in arrival order, a single out-of-line stamp taken out (module docstring).

    ``offer`` a sample, get back the samples it released, in arrival order (a normal sample at once; a
    suspect one when the next sample decides it); ``flush`` when the input ended. ``dropped``: the stamps
    taken out, in order. Pure: no clock, no ROS."""

    def __init__(self, min_jump_ns: int) -> None:
        self.min_jump = min_jump_ns
        self.last: int | None = None  # the last stamp released
        self.dropped: list[int] = []
        self._intervals: deque[int] = deque(maxlen=TYPICAL_INTERVALS)
        self._held: list[tuple[int, Any]] = []

    @property
    def jump_ns(self) -> int:
        typical = sorted(self._intervals)[len(self._intervals) // 2] if self._intervals else 0
        return max(self.min_jump, OUTLIER_INTERVALS * typical)

    def offer(self, stamp: int, item: Any) -> list[tuple[int, Any]]:
        self._held.append((stamp, item))
        return self._resolve(final=False)

    def flush(self) -> list[tuple[int, Any]]:
        return self._resolve(final=True)

    def _resolve(self, final: bool) -> list[tuple[int, Any]]:
        out: list[tuple[int, Any]] = []
        held, jump = self._held, self.jump_ns
        while held:
            s = held[0][0]
            if self.last is None:  # the first sample: kept once a second one agrees with it
                if len(held) >= 2 and abs(held[1][0] - s) <= jump:
                    out.append(self._release())
                elif len(held) >= 3:  # a and b disagree: c says which one is out of line
                    b, c = held[1][0], held[2][0]
                    if abs(c - b) <= jump and abs(c - s) > jump:
                        self.dropped.append(held.pop(0)[0])
                    else:
                        out.append(self._release())
                elif final:  # too few samples to tell: kept
                    out.append(self._release())
                else:
                    break
            elif abs(s - self.last) <= jump:
                out.append(self._release())
            elif len(held) >= 2:  # a suspect: the next sample tells a bad stamp from a real jump
                n = held[1][0]
                if abs(n - self.last) < abs(n - s):
                    self.dropped.append(held.pop(0)[0])
                else:
                    out.append(self._release())
            elif final:  # a suspect nothing after it confirms
                self.dropped.append(held.pop(0)[0])
            else:
                break
            jump = self.jump_ns
        return out

    def _release(self) -> tuple[int, Any]:
        stamp, item = self._held.pop(0)
        if self.last is not None:
            self._intervals.append(abs(stamp - self.last))
        self.last = stamp
        return stamp, item


def typical_interval(stamps: list[int], period_ns: int) -> int:
    intervals = np.diff(np.asarray(stamps[: TYPICAL_INTERVALS + 1], dtype=np.int64))
    return int(np.median(intervals)) if len(intervals) else period_ns


@dataclass
class _Kept:
    time_ns: int
    rows: dict[str, np.ndarray]


class StepBuilder:
    """Topic samples in, decided steps out (see the module docstring).

    ``add`` a sample of any topic the mapping reads; ``take`` the steps decided since; ``finish`` when the
    input ended (decides everything left). ``drop_bad`` (live): a message that cannot be decoded drops
    its step, with a note, instead of failing the whole input (ConvertError naming ``source``, topic,
    field and time, as a bag does)."""

    def __init__(
        self,
        mapping: ConvertMapping,
        source: Path | str,
        drop_bad: bool = False,
        max_lag_ns: int | None = None,
    ) -> None:
        self.mapping, self.source, self.drop_bad = mapping, source, drop_bad
        self.max_lag_ns = max_lag_ns
        self.features = mapping.topic_features
        self.readers = {f.name: FeatureReader(f, source) for f in self.features}
        self.buffers: dict[str, TopicBuffer] = {f.topic: TopicBuffer() for f in self.features}
        # a jump shorter than two steps costs at most one step: not worth a sample's delay
        self.filters = {topic: StampFilter(2 * mapping.period_ns) for topic in self.buffers}
        self.outliers: list[str] = []  # a line per stamp outlier dropped (the first OUTLIER_NOTES a topic)
        self.primary = mapping.features[mapping.primary]
        self.markers: list[int] = []
        self.finished = False
        self._clock: StepClock | None = None
        self._primary_waiting: list[int] = []  # primary times before the clock knows the typical interval
        self._candidates: deque[int] = deque()  # step times taken by the clock, not yet decided
        self._episode: list[_Kept] = []  # the current episode's kept steps not yet handed out (+ the last)
        self._episode_length = 0  # kept observations of the current episode
        self._episode_index = 0
        self._handed_out = 0  # steps of the current episode handed out
        self._last_kept: int | None = None
        self._out: list[BuiltStep] = []
        self.unmatched: dict[str, list[int]] = {}  # feature -> [count, first time]
        self.bad: list[str] = []  # live: steps dropped for a message that could not be decoded
        self.unmatched_steps = 0  # steps where some feature had no sample within its tolerance
        self.short_episodes = 0
        self.short_steps = 0
        self.silences: list[str] = []  # live: a line each time a topic fell silent (max_lag_ns)
        self._silent: set[str] = set()  # topics reported silent, until they deliver again
        self._first_ns: int | None = None  # the oldest and newest sample times of any mapped topic
        self._newest_ns: int | None = None

    # -- input ------------------------------------------------------------------------------------

    def add(self, topic: str, stamp: int, msg: Any, msgtype: str = "") -> None:
        if topic == self.mapping.marker_topic:
            bisect.insort(self.markers, stamp)
        stamp_filter = self.filters.get(topic)
        if stamp_filter is None:
            return
        for kept, kept_msg in stamp_filter.offer(stamp, msg):
            self._add_sample(topic, kept, kept_msg, msgtype)
        self._report_outliers(topic)

    def _add_sample(self, topic: str, stamp: int, msg: Any, msgtype: str) -> None:
        buffer = self.buffers[topic]
        buffer.msgtype = buffer.msgtype or msgtype
        buffer.add(stamp, msg)
        self._first_ns = stamp if self._first_ns is None else min(self._first_ns, stamp)
        self._newest_ns = stamp if self._newest_ns is None else max(self._newest_ns, stamp)
        horizon = self._horizon()
        if topic in self._silent and (horizon is None or buffer.latest >= horizon):
            self._silent.discard(topic)  # it delivers again: a next silence is reported anew
        if topic == self.primary.topic:
            self._primary_sample(stamp)

    def add_sorted(
        self,
        topic: str,
        stamps: list[int],
        messages: list[Any],
        msgtype: str,
        arrival: Sequence[int] | None = None,
    ) -> None:
        """All of a topic's samples at once, in time order (a bag): the same as adding them one by one in
        the order ``arrival`` ranks them (each sample's arrival index; None: time order), the topic's
        input then ending."""
        if topic == self.mapping.marker_topic:
            self.markers = sorted([*self.markers, *stamps])
        buffer = self.buffers.get(topic)
        if buffer is None or not stamps:
            return
        if buffer.stamps:
            raise PlaysegError(f"add_sorted: topic {topic} has samples already")
        stamp_filter = self.filters[topic]
        order = np.argsort(np.asarray(arrival), kind="stable") if arrival is not None else range(len(stamps))
        kept = np.zeros(len(stamps), dtype=bool)
        for i in order:
            for _, index in stamp_filter.offer(stamps[i], i):
                kept[index] = True
        for _, index in stamp_filter.flush():
            kept[index] = True
        self._report_outliers(topic)
        if not kept.all():
            stamps = [t for t, k in zip(stamps, kept, strict=True) if k]
            messages = [m for m, k in zip(messages, kept, strict=True) if k]
        if not stamps:
            return
        buffer.msgtype = buffer.msgtype or msgtype
        buffer.stamps, buffer.messages = list(stamps), list(messages)
        buffer.latest, buffer._array = max(stamps), None
        self._first_ns = min(stamps[0], self._first_ns if self._first_ns is not None else stamps[0])
        self._newest_ns = max(stamps[-1], self._newest_ns if self._newest_ns is not None else stamps[-1])
        if topic == self.primary.topic:
            for stamp in stamps:
                self._primary_sample(stamp)

    def _report_outliers(self, topic: str) -> None:
        stamp_filter = self.filters[topic]
        reported = sum(1 for line in self.outliers if line.startswith(f"topic {topic}: "))
        for stamp in stamp_filter.dropped[reported:OUTLIER_NOTES]:
            last = stamp_filter.last
            off = "" if last is None else f", {(stamp - last) / 1e9:+.3f} s from the samples around it"
            more = (
                " (further outliers of this topic are only counted)" if reported == OUTLIER_NOTES - 1 else ""
            )
            self.outliers.append(
                f"topic {topic}: sample stamped {stamp / 1e9:.3f} s dropped as a stamp outlier{off}{more}"
            )
            reported += 1

    def _primary_sample(self, stamp: int) -> None:
        if self._clock is None:
            self._primary_waiting.append(stamp)
            if len(self._primary_waiting) > TYPICAL_INTERVALS:
                self._start_clock()
        elif self._clock.offer(stamp):
            self._candidates.append(stamp)

    def _start_clock(self) -> None:
        gap = self.mapping.gap_ns if self.mapping.split == "gap" else None
        typical = typical_interval(self._primary_waiting, self.mapping.period_ns)
        self._clock = StepClock(self.mapping.period_ns, typical, gap)
        for stamp in self._primary_waiting:
            if self._clock.offer(stamp):
                self._candidates.append(stamp)
        self._primary_waiting = []

    # -- output -----------------------------------------------------------------------------------

    def take(self) -> list[BuiltStep]:
        """The steps decided since the last call, in order."""
        horizon = self._horizon()
        while self._candidates and (
            self._decidable(self._candidates[0]) or (horizon is not None and self._candidates[0] < horizon)
        ):
            self._decide(self._candidates.popleft())
        out, self._out = self._out, []
        return out

    def finish(self) -> list[BuiltStep]:
        """The input ended: decide every remaining step and end the last episode."""
        self.finished = True
        for topic, stamp_filter in self.filters.items():
            for stamp, msg in stamp_filter.flush():
                self._add_sample(topic, stamp, msg, "")
            self._report_outliers(topic)
        if self._clock is None and self._primary_waiting:
            self._start_clock()
        out = self.take()
        self._end_episode()
        return out + self.take()

    def prune(self) -> None:
        """Live: forget samples no undecided step can match (bounded memory). With ``max_lag_ns`` also
        those older than the horizon when no step waits (the primary is silent), and report each topic
        that fell silent in `silences`."""
        horizon = self._horizon()
        if horizon is not None:
            self._report_silent(horizon)
        oldest = self._candidates[0] if self._candidates else horizon
        if oldest is None:
            return
        for feature in self.features:
            self.buffers[feature.topic].prune(oldest - feature.tolerance_ns - 1)

    def _horizon(self) -> int | None:
        """Steps and samples older than this are decided / forgotten (None: unbounded)."""
        if self.max_lag_ns is None or self._newest_ns is None:
            return None
        return self._newest_ns - self.max_lag_ns

    def _report_silent(self, horizon: int) -> None:
        newest_topic = max(self.buffers, key=lambda t: self.buffers[t].latest or 0)
        for topic, buffer in self.buffers.items():
            last = buffer.latest if buffer.latest is not None else self._first_ns
            if topic in self._silent or last >= horizon:
                continue
            self._silent.add(topic)
            lag = f"{(self._newest_ns - last) / 1e9:.3f} s"
            since = f"no sample yet, {lag}" if buffer.latest is None else f"its newest sample is {lag}"
            self.silences.append(
                f"topic {topic} is silent: {since} behind {newest_topic} (more than max_lag "
                f"{self.max_lag_ns / 1e9:g} s); steps are decided without waiting for it (dropped where it "
                "has no sample within tolerance) and older samples of "
                "the other topics are dropped"
            )

    @property
    def episodes_kept(self) -> int:
        """Episodes handed out to their last step."""
        return self._episode_index

    @property
    def dropped_steps(self) -> int:
        missing = self._clock.missing if self._clock else 0
        return missing + self.unmatched_steps + self.short_steps + len(self.bad)

    def notes(self) -> list[str]:
        notes = []
        if self._clock and self._clock.missing:
            first = (self._clock.first_gap or 0) / 1e9
            notes.append(
                f"primary clock: {self._clock.missing} step(s) missing in gaps, first after {first:.3f}"
            )
        for feature in self.features:
            if feature.name in self.unmatched:
                count, first = self.unmatched[feature.name]
                notes.append(
                    f"{feature.name} ({feature.topic}): {count} step(s) without a sample within "
                    f"{feature.tolerance_ns / 1e6:g} ms ({feature.align}); dropped, "
                    f"first at {first / 1e9:.3f}"
                )
        for topic, stamp_filter in self.filters.items():
            if stamp_filter.dropped:
                notes.append(
                    f"topic {topic}: {len(stamp_filter.dropped)} sample(s) dropped as stamp outliers (far "
                    f"from the samples around them), first stamped {stamp_filter.dropped[0] / 1e9:.3f} s"
                )
        if self.short_episodes:
            notes.append(
                f"{self.short_episodes} episode(s) with fewer than {self.mapping.min_steps} steps; dropped"
            )
        return notes + self.bad

    def schema(self) -> Features:
        """The features of the steps (known once a step was decoded)."""
        schemas = [self.readers[f.name].schema() for f in self.features]
        action = self.mapping.action
        if isinstance(action, DerivedAction):
            source = next(f for f in schemas if f.name == action.of)
            schemas.append(
                Feature(
                    ACTION, "action", "float32", source.shape, source.names, low=action.low, high=action.high
                )
            )
        return Features.of(schemas, self.mapping.fps)

    # -- deciding ---------------------------------------------------------------------------------

    def _decidable(self, step_ns: int) -> bool:
        if self.finished:
            return True
        for feature in self.features:
            latest = self.buffers[feature.topic].latest
            if latest is None or latest <= step_ns + feature.tolerance_ns:
                return False
        return True

    def _decide(self, step_ns: int) -> None:
        alignments = {}
        matched = True
        for feature in self.features:
            alignment = self.readers[feature.name].match(step_ns, self.buffers[feature.topic])
            alignments[feature.name] = alignment
            if not alignment.matched[0]:
                matched = False
                count = self.unmatched.setdefault(feature.name, [0, step_ns])
                count[0] += 1
        if not matched:
            self.unmatched_steps += 1
            return
        try:
            rows = {
                f.name: self.readers[f.name].decode(alignments[f.name], self.buffers[f.topic])
                for f in self.features
            }
        except ConvertError as error:
            if not self.drop_bad:
                raise
            self.bad.append(f"step at {step_ns / 1e9:.3f} dropped: {error}")
            return
        self._keep(_Kept(step_ns, rows))

    def _keep(self, kept: _Kept) -> None:
        if self._last_kept is not None and self._starts_episode(self._last_kept, kept.time_ns):
            self._end_episode()
        self._last_kept = kept.time_ns
        self._episode.append(kept)
        self._episode_length += 1
        if self._episode_length >= self.mapping.min_steps + 1:  # the episode will be kept: hand out
            while len(self._episode) > 1:
                self._hand_out(self._episode[0], self._episode[1])
                self._episode.pop(0)

    def _starts_episode(self, previous_ns: int, step_ns: int) -> bool:
        if self.mapping.split == "gap" and self.mapping.gap_ns is not None:
            return step_ns - previous_ns > self.mapping.gap_ns
        if self.mapping.split == "marker":
            i = bisect.bisect_left(self.markers, previous_ns + 1)
            return i < len(self.markers) and self.markers[i] <= step_ns
        return False

    def _end_episode(self) -> None:
        if not self._episode:
            return
        if self._episode_length >= self.mapping.min_steps + 1:
            while len(self._episode) > 1:
                self._hand_out(self._episode[0], self._episode[1])
                self._episode.pop(0)
            self._hand_out(self._episode[0], None)
            self._episode_index += 1
        else:
            self.short_episodes += 1
            self.short_steps += self._episode_length
        self._episode, self._episode_length, self._handed_out = [], 0, 0

    def _hand_out(self, kept: _Kept, following: _Kept | None) -> None:
        action = None
        if following is not None:
            derived = self.mapping.action
            if isinstance(derived, DerivedAction):
                now, then = kept.rows[derived.of], following.rows[derived.of]
                action = then - now if derived.derive == "delta" else then
            else:
                action = kept.rows[ACTION]
            action = np.ascontiguousarray(action, dtype=np.float32)
        observation = {name: kept.rows[name] for name in self.mapping.features}
        self._out.append(
            BuiltStep(
                self._episode_index, self._handed_out, kept.time_ns, observation, action, following is None
            )
        )
        self._handed_out += 1

"""Message definitions of playseg_msgs for bag I/O without a ROS graph.

The `.msg` files are read from the installed interface package (``<prefix>/share/playseg_msgs/msg``) or,
in a source checkout, from ``msg_defs/playseg_msgs/msg``. From them we build a `rosbags` typestore (for
CDR (de)serialization without rclpy) and the full ``ros2msg`` schema text that rosbag2 writes into MCAP
files (the message definition followed by each dependency, separated by ``=`` lines).
"""

from __future__ import annotations

import sys
from functools import cache
from pathlib import Path
from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from playseg_core.errors import PlaysegError

PLAYSEG_MSG_TYPES = ("PlayStep", "Annotation", "TimedAnnotation", "LabelledSegment", "TrainerStatus")
_REPO_MSG_DIR = Path(__file__).resolve().parent.parent / "msg_defs" / "playseg_msgs" / "msg"


def split_type_name(type_name: str) -> tuple[str, str]:
    """'pkg/msg/Type' or 'pkg/Type' -> ('pkg', 'Type')."""
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg" and all(parts):
        return parts[0], parts[2]
    if len(parts) == 2 and all(parts):
        return parts[0], parts[1]
    raise PlaysegError(f"message type name {type_name!r} is not 'package/msg/Type' or 'package/Type'")


def msg_dir() -> Path:
    """Directory holding playseg_msgs' .msg files: the built interface package's, else the copy that
    playseg's own install carries (the I/O part alone has no interface package), else the source tree."""
    candidates = [Path(sys.prefix) / "share" / name / "msg" for name in ("playseg_msgs", "playseg_ros")]
    for candidate in (*candidates, _REPO_MSG_DIR):
        if (candidate / "PlayStep.msg").is_file():
            return candidate
    raise FileNotFoundError(
        f"playseg_msgs .msg files not found in {', '.join(map(str, candidates))} or {_REPO_MSG_DIR}"
    )


def msg_text(name: str) -> str:
    """The .msg definition of playseg_msgs/msg/<name>."""
    return (msg_dir() / f"{name}.msg").read_text()


@cache
def playseg_typestore() -> Typestore:
    """A rosbags typestore with ROS 2 Kilted's standard types plus playseg_msgs."""
    store = get_typestore(Stores.ROS2_KILTED)
    types = {}
    for name in PLAYSEG_MSG_TYPES:
        types.update(get_types_from_msg(msg_text(name), f"playseg_msgs/msg/{name}"))
    store.register(types)
    return store


PLAY_STEP_BEFORE_CAMERAS = """\
std_msgs/Header header
string episode_id
uint32 step
sensor_msgs/Image observation
float32[] state
uint32[] state_shape
float32[] action
bool episode_end
"""
"""PlayStep as bags recorded before it carried several cameras hold it (no camera_names,
extra_observations): kept so that those bags still read."""


TRAINER_STATUS_BEFORE_METRIC = """\
std_msgs/Header header
string state
uint64 buffer_segments
uint64 buffer_steps
uint32 policy_version
string checkpoint_path
float32 last_eval_success_rate
uint32 last_eval_episodes
float32 last_train_loss
string message
"""
"""TrainerStatus as bags recorded before it said which evaluation it reports (no last_eval_metric,
last_eval_value)."""

LABELLED_SEGMENT_BEFORE_REFERENCE = """\
std_msgs/Header header
string episode_id
uint32 start_step
uint32 end_step
string instruction
float32 label_confidence
float32 segment_log_prob
string model_id
PlayStep[] steps
"""
"""LabelledSegment as bags recorded before it had a reference form (no recording_bag, steps_topic,
first_step_stamp, last_step_stamp)."""

EARLIER_GENERATIONS: tuple[dict[str, str], ...] = (
    {"LabelledSegment": LABELLED_SEGMENT_BEFORE_REFERENCE},
    {
        "PlayStep": PLAY_STEP_BEFORE_CAMERAS,
        "TrainerStatus": TRAINER_STATUS_BEFORE_METRIC,
        "LabelledSegment": LABELLED_SEGMENT_BEFORE_REFERENCE,
    },
)
"""Earlier definitions by generation, newest first; a type not named has today's definition there. A
generation is one typestore because a message embedding another (LabelledSegment's PlaySteps) has the
hash of the definitions of its time together."""


@cache
def earlier_typestores() -> tuple[Typestore, ...]:
    """Typestores of earlier playseg_msgs definitions that bags may still hold, newest first."""
    stores = []
    for generation in EARLIER_GENERATIONS:
        store = get_typestore(Stores.ROS2_KILTED)
        types = {}
        for name in PLAYSEG_MSG_TYPES:
            text = generation.get(name) or msg_text(name)
            types.update(get_types_from_msg(text, f"playseg_msgs/msg/{name}"))
        store.register(types)
        stores.append(store)
    return tuple(stores)


@cache
def typestore_for(type_name: str, type_hash: str) -> Typestore | None:
    """The typestore whose ``type_name`` has the RIHS01 ``type_hash`` a bag records: today's definitions
    or an earlier one; today's for a bag that records no hash; None when no known definition matches."""
    if not type_hash.startswith("RIHS01_"):
        return playseg_typestore()
    for store in (playseg_typestore(), *earlier_typestores()):
        if type_name in store.fielddefs and store.hash_rihs01(type_name) == type_hash:
            return store
    return None


def _as_current(value: Any, old: Typestore, new: Typestore) -> Any:
    """A message object of ``old``'s classes rebuilt with ``new``'s: fields both define are copied
    (nested messages rebuilt alike), fields only ``new`` defines get their empty value (an empty
    sequence or string, NaN for a float, 0 for an integer)."""
    type_name = getattr(value, "__msgtype__", None)
    if type_name is None:
        if isinstance(value, list):
            return [_as_current(item, old, new) for item in value]
        return value  # numbers, strings, numpy arrays
    _, fields = new.fielddefs[type_name]
    values = {}
    for name, (node_type, field_type) in fields:
        if hasattr(value, name):
            values[name] = _as_current(getattr(value, name), old, new)
        else:
            values[name] = _empty(f"{type_name}.{name}", node_type, field_type, new)
    return new.types[type_name](**values)


def _empty(where: str, node_type: int, field_type: Any, store: Typestore) -> Any:
    """The value of a field earlier definitions lack (a nested message: each of its fields empty)."""
    if node_type == _SEQUENCE:
        return []
    if node_type == _BASE:
        return _EMPTY_BASE.get(field_type[0], 0)
    if node_type == _NAME:
        _, fields = store.fielddefs[field_type]
        return store.types[field_type](
            **{name: _empty(f"{where}.{name}", kind, inner, store) for name, (kind, inner) in fields}
        )
    raise PlaysegError(f"{where}: no value for a field earlier definitions lack")


_BASE, _NAME, _SEQUENCE = 1, 2, 4  # rosbags' Nodetype values of a base type, a message and a sequence
_EMPTY_BASE = {"string": "", "float32": float("nan"), "float64": float("nan"), "bool": False}
"""The value a field earlier definitions lack gets (a figure not recorded is NaN; integers get 0)."""


def as_current_cdr(data: bytes, type_name: str, type_hash: str) -> bytes:
    """A recorded message's CDR in today's definition of ``type_name`` (re-encoded when the bag holds
    an earlier one), so a bag from before a definition changed still plays to today's subscribers;
    ValueError when the recorded definition is unknown."""
    store = typestore_for(type_name, type_hash)
    current = playseg_typestore()
    if store is None:
        raise PlaysegError(f"{type_name}: unknown definition (type hash {type_hash})")
    if store is current:
        return data
    message = _as_current(store.deserialize_cdr(data, type_name), store, current)
    return bytes(current.serialize_cdr(message, type_name))

"""Messages to feature rows: camera images to (H, W, 3) uint8, numeric fields to float32 vectors.

Images: ``sensor_msgs/msg/CompressedImage`` (whatever OpenCV decodes: jpeg, png) and ``sensor_msgs/msg/Image``
in rgb8, bgr8, rgba8, bgra8, mono8 (grey is repeated into 3 channels). 16-bit depth (16UC1, mono16, or a
16-bit png) becomes its own camera feature, packed losslessly into the image format: red = high byte,
green = low byte, blue = 0 (depth = 256 * R + G), because a dataset camera is (H, W, 3) uint8.

Numbers: dotted paths into the message (``linear.x``, ``pose.pose.position.x``, ``position``), an array
element as ``data[2]``; a JointState's ``position``/``velocity``/``effort`` are ordered by joint name
(the first message's order, or the mapping's ``joints``), and the joint names become the feature's names.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from playseg_core.errors import PlaysegError

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
JOINT_STATE = "sensor_msgs/msg/JointState"
JOINT_FIELDS = ("position", "velocity", "effort")
COLOUR_ENCODINGS = {"rgb8": (3, None), "bgr8": (3, cv2.COLOR_BGR2RGB), "8UC3": (3, cv2.COLOR_BGR2RGB),
                    "rgba8": (4, cv2.COLOR_RGBA2RGB), "bgra8": (4, cv2.COLOR_BGRA2RGB),
                    "mono8": (1, cv2.COLOR_GRAY2RGB), "8UC1": (1, cv2.COLOR_GRAY2RGB)}  # fmt: skip
DEPTH_ENCODINGS = ("16UC1", "mono16")
_INDEXED = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)\[(\d+)\]$")


class DecodeError(PlaysegError):
    """A message that does not give the feature asked for; ``field`` names the part at fault."""

    def __init__(self, detail: str, field: str | None = None) -> None:
        self.field = field
        super().__init__(detail)


# --------------------------------------------------------------------------------------------------
# Images


def pack_depth(depth: np.ndarray) -> np.ndarray:
    """(H, W) uint16 depth -> (H, W, 3) uint8: red = high byte, green = low byte, blue = 0."""
    packed = np.zeros((*depth.shape, 3), dtype=np.uint8)
    packed[..., 0] = depth >> 8
    packed[..., 1] = depth & 0xFF
    return packed


def unpack_depth(packed: np.ndarray) -> np.ndarray:
    """The inverse of `pack_depth`."""
    return packed[..., 0].astype(np.uint16) << 8 | packed[..., 1].astype(np.uint16)


def decode_image(msg: Any, msgtype: str, resize: tuple[int, int] | None = None) -> np.ndarray:
    """An Image or CompressedImage message as (H, W, 3) uint8 RGB, 16-bit depth packed (``resize``: (width,
    height))."""
    if msgtype == COMPRESSED_IMAGE:
        image = _decode_compressed(msg)
    elif msgtype == IMAGE:
        image = _decode_raw(msg)
    else:
        raise DecodeError(f"type {msgtype} is not an image (expected {' or '.join(IMAGE_TYPES)})")
    is_depth = image.dtype == np.uint16
    if resize is not None and (image.shape[1], image.shape[0]) != resize:
        # area averaging for colour; depth keeps measured values (no averaging across an edge)
        image = cv2.resize(image, resize, interpolation=cv2.INTER_NEAREST if is_depth else cv2.INTER_AREA)
    return pack_depth(image) if is_depth else np.ascontiguousarray(image)


def _decode_compressed(msg: Any) -> np.ndarray:
    data = np.asarray(msg.data, dtype=np.uint8)
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None:
        raise DecodeError(f"undecodable image (format {msg.format!r}, {data.size} bytes)", "data")
    if image.dtype == np.uint16 and image.ndim == 2:
        return image
    if image.dtype != np.uint8:
        raise DecodeError(
            f"image of {image.dtype} (format {msg.format!r}); 8-bit or 16-bit depth expected", "data"
        )
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _decode_raw(msg: Any) -> np.ndarray:
    height, width, step, encoding = int(msg.height), int(msg.width), int(msg.step), str(msg.encoding)
    data = np.asarray(msg.data, dtype=np.uint8)
    if encoding in DEPTH_ENCODINGS:
        channels, itemsize = 1, 2
    elif encoding in COLOUR_ENCODINGS:
        channels, itemsize = COLOUR_ENCODINGS[encoding][0], 1
    else:
        known = ", ".join([*COLOUR_ENCODINGS, *DEPTH_ENCODINGS])
        raise DecodeError(f"image encoding {encoding!r} not supported (expected one of {known})", "encoding")
    row = width * channels * itemsize
    if height <= 0 or width <= 0 or step < row or data.size < step * (height - 1) + row:
        raise DecodeError(
            f"{width}x{height} {encoding} with step {step} needs {step * height} bytes, has {data.size}",
            "data",
        )
    rows = np.lib.stride_tricks.as_strided(data, (height, row), (step, 1))  # drops any row padding
    if itemsize == 2:
        depth = np.ascontiguousarray(rows).view(">u2" if msg.is_bigendian else "<u2").astype(np.uint16)
        return depth.reshape(height, width)
    image = np.ascontiguousarray(rows).reshape(height, width, channels)
    conversion = COLOUR_ENCODINGS[encoding][1]
    return image if conversion is None else cv2.cvtColor(image, conversion)


# --------------------------------------------------------------------------------------------------
# Numbers


def field_value(msg: Any, path: str) -> Any:
    """The value at dotted ``path`` (``linear.x``, ``data[2]``); DecodeError naming the missing part."""
    value = msg
    walked: list[str] = []
    for part in path.split("."):
        indexed = _INDEXED.match(part)
        name, index = (indexed.group(1), int(indexed.group(2))) if indexed else (part, None)
        walked.append(part)
        if not hasattr(value, name) or name.startswith("_"):
            have = ", ".join(
                sorted(k for k in getattr(value, "__dataclass_fields__", {}) if not k.startswith("_"))
            )
            raise DecodeError(f"not in the message (there: {have or 'no fields'})", ".".join(walked))
        value = getattr(value, name)
        if index is not None:
            try:
                value = value[index]
            except (IndexError, TypeError):
                raise DecodeError(f"no element {index}", ".".join(walked)) from None
    return value


def _numbers(value: Any, field: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float32).reshape(-1)
    except (TypeError, ValueError):
        raise DecodeError(f"not numeric ({type(value).__name__})", field) from None
    return array


@dataclass
class NumericDecoder:
    """Turns messages of one topic into float32 vectors of a fixed size; made from the topic's first message
    (sizes, joint order and names), it refuses a later message that does not fit."""

    msgtype: str
    fields: tuple[str, ...]
    joints: tuple[str, ...] | None
    sizes: tuple[int, ...]
    names: tuple[str, ...]

    @classmethod
    def of_first(
        cls, msg: Any, msgtype: str, fields: Sequence[str], joints: Sequence[str] | None
    ) -> NumericDecoder:
        is_joint_state = msgtype == JOINT_STATE and all(f in JOINT_FIELDS for f in fields)
        if joints is not None and not is_joint_state:
            raise DecodeError(
                f"'joints' selects JointState {'/'.join(JOINT_FIELDS)}; this is {msgtype}", "joints"
            )
        if is_joint_state:
            joint_order = tuple(joints) if joints is not None else tuple(str(n) for n in msg.name)
            decoder = cls(msgtype, tuple(fields), joint_order, tuple(len(joint_order) for _ in fields), ())
            single = len(fields) == 1
            names = tuple(j if single else f"{f}.{j}" for f in fields for j in joint_order)
        else:
            sizes = tuple(_numbers(field_value(msg, f), f).size for f in fields)
            decoder = cls(msgtype, tuple(fields), None, sizes, ())
            names = tuple(
                f if size == 1 else f"{f}[{i}]"
                for f, size in zip(fields, sizes, strict=True)
                for i in range(size)
            )
        decoder.names = names
        decoder.decode(msg)  # the first message must fit too
        return decoder

    @property
    def size(self) -> int:
        return sum(self.sizes)

    def decode(self, msg: Any) -> np.ndarray:
        if self.joints is not None:
            return np.concatenate([self._joint_values(msg, f) for f in self.fields]).astype(np.float32)
        parts = []
        for field, size in zip(self.fields, self.sizes, strict=True):
            values = _numbers(field_value(msg, field), field)
            if values.size != size:
                raise DecodeError(f"{values.size} values, the topic's first message had {size}", field)
            parts.append(values)
        return np.concatenate(parts)

    def _joint_values(self, msg: Any, field: str) -> np.ndarray:
        assert self.joints is not None
        values = np.asarray(getattr(msg, field), dtype=np.float32)
        names = [str(n) for n in msg.name]
        if values.size != len(names):
            raise DecodeError(f"{values.size} values for {len(names)} joint names", field)
        if tuple(names) == self.joints:
            return values
        index = {n: i for i, n in enumerate(names)}
        missing = [j for j in self.joints if j not in index]
        if missing:
            raise DecodeError(f"joint(s) {missing} not in this message (it has {names})", field)
        return values[[index[j] for j in self.joints]]

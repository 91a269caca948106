"""The topics of a session, the schemas of its messages, and the one way its messages are decoded."""

from __future__ import annotations

import json
import re
import struct
from typing import Any, Callable

import foxglove
import numpy as np
from mcap.records import Channel, Schema
from mcap_protobuf.decoder import DecoderFactory
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

from capture.source import SourceError

MCAP_MAGIC = b"\x89MCAP0\r\n"
ROS2_IMAGE_SCHEMA = foxglove.Schema(name="sensor_msgs/msg/Image", encoding="ros2msg", data=b"""\
std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
""")
CDR_LITTLE_ENDIAN = b"\x00\x01\x00\x00"
CAMERA_TOPIC = re.compile(r"^/camera/(?P<sensor>.+)/(?P<kind>depth|color|calibration|meta)$")
META_SCHEMA = {
    "title": "mushroom_pose.DepthFrameMeta",
    "type": "object",
    "properties": {
        "timestamp_ns": {"type": "integer"},
        "depth_scale": {"type": "number", "description": "metres per depth unit"},
        "turntable_angle": {"type": ["number", "null"], "description": "radians"},
        "T_world_camera": {"type": ["array", "null"], "items": {"type": "number"},
                           "description": "row-major 4x4, exact"},
        "has_color": {"type": "boolean"},
    },
    "required": ["timestamp_ns", "depth_scale", "turntable_angle", "T_world_camera", "has_color"],
}


SESSION_TOPIC = "/session"
"""JSON, once, with the session's first frame: ``{"bed_id", "started_ns"}``, which bed it scans (None:
not said) and when it began, so scans of one bed over days can be put in order (``track``)."""
FUSED_CLOUD_TOPIC = "/fusion/cloud"
DETECTIONS_TOPIC = "/perception/mushrooms_json"
CAPS_TOPIC = "/perception/mushrooms"
CAP_OUTLINES_TOPIC = "/perception/cap_outlines"
"""The caps as wire domes in a point cloud, for viewers that draw no SceneUpdate."""
PLAN_TOPIC = "/perception/plan"
"""The pick plan as a SceneUpdate: one approach arrow per cap, its place in the order as text."""
PLAN_JSON_TOPIC = "/perception/plan_json"
"""The pick plan as the detection document's ``"plan"``, with the unit's index: what a controller reads."""
UNIT_TOPIC = "/fusion/unit"
"""JSON per fused cloud: its frames and its exact T_world_bed, so replay can start from fusion's output."""
BED_TRANSFORM_TOPIC = "/fusion/tf"
"""world -> bed of each fused cloud, for viewers: written when the unit is fused, after later frames'
/tf messages, so on a topic of its own."""


def ros2_image(timestamp_ns: int, frame_id: str, pixels: np.ndarray, encoding: str) -> bytes:
    """One sensor_msgs/msg/Image (``ROS2_IMAGE_SCHEMA``) in little-endian CDR: each field aligned to
    its size from the end of the 4-byte encapsulation header, strings as a uint32 length (with the
    terminating NUL) and the bytes, ``data`` as a uint32 length and the rows. One fixed layout, so it
    is written here; mcap-ros2-support's decoder reads it back (tested)."""
    pixels = np.ascontiguousarray(pixels)
    body = bytearray()

    def uint32(value: int) -> None:
        body.extend(b"\0" * (-len(body) % 4))
        body.extend(struct.pack("<I", value))

    def text(value: str) -> None:
        data = value.encode() + b"\0"
        uint32(len(data))
        body.extend(data)

    seconds, nanoseconds = divmod(int(timestamp_ns), 10**9)
    body.extend(struct.pack("<iI", seconds, nanoseconds))
    text(frame_id)
    uint32(pixels.shape[0])
    uint32(pixels.shape[1])
    text(encoding)
    body.append(0)  # is_bigendian
    uint32(pixels.strides[0])
    uint32(pixels.nbytes)
    return CDR_LITTLE_ENDIAN + bytes(body) + pixels.tobytes()


class Decoders:
    """Decodes the messages of a file's channels: JSON to dicts, foxglove protobuf and ROS 2 CDR to
    their messages; a decoder is looked up once per channel. Any other encoding is a SourceError."""

    def __init__(self, path: Any) -> None:
        self.path = path
        self._decoders: dict[int, Callable[[bytes], Any]] = {}

    def __call__(self, schema: Schema | None, channel: Channel, data: bytes) -> Any:
        if channel.message_encoding == "json":
            return json.loads(data)
        if channel.id not in self._decoders:
            for factory in (DecoderFactory(), Ros2DecoderFactory()):
                decoder = factory.decoder_for(channel.message_encoding, schema)
                if decoder is not None:
                    self._decoders[channel.id] = decoder
                    break
            else:
                raise SourceError(f"{self.path}: {channel.topic} is {channel.message_encoding}, "
                                  "neither JSON, foxglove protobuf nor ROS 2 CDR")
        return self._decoders[channel.id](data)

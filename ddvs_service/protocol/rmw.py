"""rmw_zenoh interoperability: key expressions and the sample attachment ROS 2 (Jazzy and later) nodes expect.

rmw_zenoh_cpp publishes a topic `/<name>` of type `<pkg>/msg/<Type>` in ROS domain `<domain_id>` on the Zenoh key
`<domain_id>/<name>/<pkg>::msg::dds_::<Type>_/<type hash>` (leading/trailing '/' of the topic stripped) with the CDR
payload unchanged, and its subscriptions drop samples without a 33-byte attachment: int64 sequence number, int64
source timestamp (ns since the epoch), the byte 16 (length prefix of the gid), 16-byte publisher gid, little-endian
(Zenoh's `z_serialize` layout of that tuple).

The type hashes are RIHS01 (REP 2011) of the message definitions, identical from Humble to Kilted for these types;
`tests/test_protocol_rmw.py` recomputes them with `rosbags`.

Verified here: the key layout and the attachment bytes (against `zenoh.ext.z_serialize`), the hashes. Not verified
(no ROS 2 installation on these machines): that a live rmw_zenoh node receives the samples. The graph liveliness
tokens that make topics visible to `ros2 topic list` are not declared.
"""

from __future__ import annotations

import os
import struct
import time
from dataclasses import dataclass

from ddvs_service.protocol.errors import InconsistentMessage, TruncatedMessage

TYPE_HASHES: dict[str, str] = {
    "sensor_msgs/msg/Image": "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "sensor_msgs/msg/CameraInfo": "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
    "geometry_msgs/msg/TwistStamped": "RIHS01_5f0fcd4f81d5d06ad9b4c4c63e3ea51b82d6ae4d0558f1d475229b1121db6f64",
    "sensor_msgs/msg/JointState": "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
}
"""RIHS01 type hashes of the ROS 2 message types this protocol carries."""

ATTACHMENT_SIZE = 33
_GID_SIZE = 16
_ATTACHMENT = struct.Struct("<qqB16s")


def dds_type_name(ros_type: str) -> str:
    """`sensor_msgs/msg/Image` → `sensor_msgs::msg::dds_::Image_` (the DDS-mangled name rmw_zenoh uses)."""
    parts = ros_type.split("/")
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        raise ValueError(f"ROS type {ros_type!r}: expected '<package>/msg/<Type>'")
    return f"{parts[0]}::msg::dds_::{parts[2]}_"


def rmw_zenoh_key(domain_id: int, topic: str, ros_type: str) -> str:
    """The Zenoh key expression rmw_zenoh uses for ROS topic `topic` of `ros_type` in ROS domain `domain_id`."""
    if not 0 <= domain_id <= 232:
        raise ValueError(f"ROS domain id {domain_id}: expected an integer in [0, 232]")
    if ros_type not in TYPE_HASHES:
        raise ValueError(f"ROS type {ros_type!r} has no known type hash; expected one of {', '.join(TYPE_HASHES)}")
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(ros_type)}/{TYPE_HASHES[ros_type]}"


@dataclass(frozen=True)
class RmwAttachment:
    """The rmw_zenoh per-sample attachment: sequence number, source time (ns since the epoch), publisher gid."""

    sequence_number: int
    source_timestamp_ns: int
    gid: bytes

    def __post_init__(self) -> None:
        if len(self.gid) != _GID_SIZE:
            raise InconsistentMessage(f"rmw_zenoh gid has {len(self.gid)} bytes; expected {_GID_SIZE}")

    def encode(self) -> bytes:
        return _ATTACHMENT.pack(self.sequence_number, self.source_timestamp_ns, _GID_SIZE, self.gid)

    @classmethod
    def decode(cls, buf: bytes | bytearray | memoryview) -> RmwAttachment:
        if len(buf) != ATTACHMENT_SIZE:
            error = TruncatedMessage if len(buf) < ATTACHMENT_SIZE else InconsistentMessage
            raise error(f"rmw_zenoh attachment has {len(buf)} bytes; expected {ATTACHMENT_SIZE}")
        seq, stamp, gid_len, gid = _ATTACHMENT.unpack(bytes(buf))
        if gid_len != _GID_SIZE:
            raise InconsistentMessage(f"rmw_zenoh attachment gid length byte is {gid_len}; expected {_GID_SIZE}")
        return cls(seq, stamp, gid)


class RmwPublisherIdentity:
    """One publisher's random gid and sequence counter; `next_attachment()` gives the bytes for each sample."""

    def __init__(self, gid: bytes | None = None) -> None:
        self.gid = gid if gid is not None else os.urandom(_GID_SIZE)
        self._sequence = 0

    def next_attachment(self, source_timestamp_ns: int | None = None) -> bytes:
        """Attachment for the next sample (sequence numbers start at 1; time defaults to now)."""
        self._sequence += 1
        stamp = time.time_ns() if source_timestamp_ns is None else source_timestamp_ns
        return RmwAttachment(self._sequence, stamp, self.gid).encode()

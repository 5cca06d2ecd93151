"""rmw_zenoh interoperability: the key expressions and the sample attachment of ROS 2 (Jazzy and later) over Zenoh.

rmw_zenoh_cpp publishes a topic `/<name>` of type `<pkg>/msg/<Type>` in ROS domain `<domain_id>` on the Zenoh key
`<domain_id>/<name>/<pkg>::msg::dds_::<Type>_/<type hash>` (leading/trailing '/' of the topic stripped) with the CDR
payload unchanged; a service `/<name>` of type `<pkg>/srv/<Type>` is a queryable on
`<domain_id>/<name>/<pkg>::srv::dds_::<Type>_/<type hash>`. Its subscriptions drop samples without a 33-byte
attachment: int64 sequence number, int64 source timestamp (ns since the epoch), the byte 16 (length prefix of the
gid), 16-byte gid, little-endian (Zenoh's `z_serialize` layout of that tuple); service requests carry the client's
and replies echo its sequence number and gid.

The type hashes are RIHS01 (REP 2011) of the definitions, identical in Jazzy and Kilted for these types;
`tests/test_protocol_keys.py` recomputes them with `rosbags` and reads them from the Kilted wheels. The ROS graph
(liveliness tokens) is `ros_graph.py`.
"""

from __future__ import annotations

import os
import struct
import time
from dataclasses import dataclass

from ddvs_service.protocol.errors import InconsistentMessage, TruncatedMessage

TYPE_HASHES: dict[str, str] = {
    "sensor_msgs/msg/Image": "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "sensor_msgs/msg/CompressedImage": "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a",
    "sensor_msgs/msg/CameraInfo": "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
    "geometry_msgs/msg/TwistStamped": "RIHS01_5f0fcd4f81d5d06ad9b4c4c63e3ea51b82d6ae4d0558f1d475229b1121db6f64",
    "sensor_msgs/msg/JointState": "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
    "std_msgs/msg/Float64MultiArray": "RIHS01_1025ddc6b9552d191f89ef1a8d2f60f3d373e28b283d8891ddcc974e8c55397f",
    "std_srvs/srv/Trigger": "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f",
}
"""RIHS01 type hashes of the ROS 2 message and service types this protocol carries."""

ATTACHMENT_SIZE = 33
_GID_SIZE = 16
_ATTACHMENT = struct.Struct("<qqB16s")


def dds_type_name(ros_type: str) -> str:
    """`sensor_msgs/msg/Image` → `sensor_msgs::msg::dds_::Image_`, `std_srvs/srv/Trigger` →
    `std_srvs::srv::dds_::Trigger_` (the DDS-mangled names rmw_zenoh uses in keys and liveliness tokens)."""
    parts = ros_type.split("/")
    if len(parts) != 3 or parts[1] not in ("msg", "srv") or not all(parts):
        raise ValueError(f"ROS type {ros_type!r}: expected '<package>/msg/<Type>' or '<package>/srv/<Type>'")
    return f"{parts[0]}::{parts[1]}::dds_::{parts[2]}_"


def ros_type_name(dds_type: str) -> str:
    """`sensor_msgs::msg::dds_::Image_` → `sensor_msgs/msg/Image` (the inverse of `dds_type_name`)."""
    parts = dds_type.split("::")
    if len(parts) != 4 or parts[1] not in ("msg", "srv") or parts[2] != "dds_" or not parts[3].endswith("_"):
        raise ValueError(f"DDS type name {dds_type!r}: expected '<package>::msg|srv::dds_::<Type>_'")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def rmw_zenoh_key(domain_id: int, topic: str, ros_type: str) -> str:
    """The Zenoh key expression rmw_zenoh uses for ROS topic (or service) `topic` of `ros_type` in `domain_id`."""
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

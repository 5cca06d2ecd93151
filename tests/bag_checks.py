"""What a bag must satisfy to be read by other tools: every message of its rosbag2 storage file decodes with the
`rosbags` rosbag2 reader and with `mcap_ros2` (each with the bag's own message definitions), every message of its
JSON file parses as a JSON object, and each MCAP file's summary lists every channel with the number of messages a
full read finds."""

from __future__ import annotations

import json
from pathlib import Path

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader

from clients.bag import iter_messages, storage_files


def summary_counts(bag: Path) -> dict[str, int]:
    """Messages per topic from the `mcap` reader's summary of both files (a channel without messages: 0)."""
    counts: dict[str, int] = {}
    for path in storage_files(bag):
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        assert summary is not None and summary.statistics is not None, f"{path} has no summary"
        for channel_id, channel in summary.channels.items():
            counts[channel.topic] = summary.statistics.channel_message_counts.get(channel_id, 0)
    return counts


def check_bag(bag: Path) -> dict[str, int]:
    """The checks of the module docstring; returns the messages decoded per topic."""
    decoded: dict[str, int] = {}
    with AnyReader([bag]) as reader:
        for connection, _, raw in reader.messages():
            reader.deserialize(raw, connection.msgtype)
            decoded[connection.topic] = decoded.get(connection.topic, 0) + 1
    with open(storage_files(bag)[0], "rb") as f:  # the mcap library's own ros2msg decoder agrees on every message
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        mcap_decoded = sum(1 for *_, message in reader.iter_decoded_messages() if message is not None)
    assert mcap_decoded == sum(decoded.values())
    for message in iter_messages(storage_files(bag)[1]):
        assert message.message_encoding == "json" and isinstance(json.loads(message.data), dict), message.topic
        decoded[message.topic] = decoded.get(message.topic, 0) + 1
    assert {t: n for t, n in summary_counts(bag).items() if n} == decoded
    return decoded

"""Zenoh session configuration (file, environment, CLI) and a real loopback round trip."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pytest

from ddvs_service.protocol import (
    Header,
    Keys,
    LatestSubscriber,
    SessionConfig,
    Time,
    add_zenoh_arguments,
    declare_publisher,
    decode_image,
    encode_image,
    image_from_array,
    open_session,
    session_config_from_args,
)


def parse(argv: list[str], environ: dict[str, str] | None = None) -> SessionConfig:
    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser)
    return session_config_from_args(parser.parse_args(argv), environ or {})


def test_defaults_are_peer_without_multicast() -> None:
    cfg = parse([])
    assert (cfg.mode, cfg.connect, cfg.listen, cfg.multicast_scouting, cfg.shm) == ("peer", [], [], False, True)
    zcfg = cfg.to_zenoh_config()
    assert json.loads(zcfg.get_json("mode")) == "peer"
    assert json.loads(zcfg.get_json("scouting/multicast/enabled")) is False


def test_cli_overrides_environment_overrides_defaults() -> None:
    env = {"DDVS_ZENOH_MODE": "client", "DDVS_ZENOH_CONNECT": "tcp/10.0.0.1:7447, tcp/10.0.0.2:7447"}
    assert parse([], env).connect == ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]
    cfg = parse(
        ["--mode", "router", "--listen", "tcp/127.0.0.1:7000,udp/127.0.0.1:7001", "--listen", "tcp/[::1]:1"], env
    )
    assert cfg.mode == "router"
    assert cfg.listen == ["tcp/127.0.0.1:7000", "udp/127.0.0.1:7001", "tcp/[::1]:1"]
    assert cfg.connect == ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]
    zcfg = cfg.to_zenoh_config()
    assert json.loads(zcfg.get_json("listen/endpoints")) == cfg.listen
    assert json.loads(zcfg.get_json("connect/endpoints")) == cfg.connect


def test_invalid_settings_name_the_source() -> None:
    with pytest.raises(ValueError, match="environment"):
        parse([], {"DDVS_ZENOH_MODE": "satellite"})
    with pytest.raises(ValueError, match="expected '<protocol>/<address>'"):
        parse(["--connect", "127.0.0.1:7447"])
    with pytest.raises(ValueError, match="client mode needs a router endpoint"):
        parse(["--mode", "client"])


def test_file_settings_and_zenoh_json5_base_with_overrides(tmp_path: Path) -> None:
    base = tmp_path / "zenoh.json5"
    base.write_text("{ // a Zenoh JSON5 file\n  queries_default_timeout: 1234, }\n", encoding="utf-8")
    settings = tmp_path / "session.json"
    settings.write_text(
        json.dumps({"mode": "peer", "listen": ["tcp/127.0.0.1:0"], "zenoh_config": str(base),
                    "overrides": {"transport/link/tx/lease": 4321}}),
        encoding="utf-8",
    )  # fmt: skip
    zcfg = SessionConfig.from_file(settings).to_zenoh_config()
    assert json.loads(zcfg.get_json("queries_default_timeout")) == 1234
    assert json.loads(zcfg.get_json("transport/link/tx/lease")) == 4321
    assert json.loads(zcfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    with pytest.raises(ValueError, match="session configuration file"):
        SessionConfig.from_file(tmp_path / "missing.json")


def test_loopback_round_trip_keeps_only_the_newest_frame(port: int) -> None:
    keys = Keys(robot="loopback")
    listener = SessionConfig(listen=[f"tcp/127.0.0.1:{port}"])
    connector = SessionConfig(connect=[f"tcp/127.0.0.1:{port}"])
    with (
        open_session(listener) as sub_session,
        open_session(connector) as pub_session,
        LatestSubscriber(sub_session, keys.camera_image) as frames,
    ):
        publisher = declare_publisher(pub_session, keys, "camera_image")
        # wait until the subscription has propagated: probe frames until one arrives
        deadline = time.monotonic() + 10.0
        while frames.recv(timeout=0.05) is None:
            assert time.monotonic() < deadline, "no sample crossed the loopback link within 10 s"
            publisher.put(encode_image(image_from_array(np.zeros((2, 2), np.uint8), "mono8")))
        while frames.recv(timeout=0.3) is not None:  # drain probes still in flight
            pass
        burst = [np.full((48, 64), i, np.uint8) for i in range(20)]
        for i, pixels in enumerate(burst):
            publisher.put(encode_image(image_from_array(pixels, "mono8", Header(Time(0, i), "cam"))))
        time.sleep(0.5)  # let the whole burst arrive while nobody reads
        sample = frames.recv(timeout=2.0)
        assert sample is not None
        newest = decode_image(sample.payload.to_bytes())
        assert newest.header.stamp.nanosec == 19
        np.testing.assert_array_equal(newest.array, burst[-1])
        assert frames.recv(timeout=0.2) is None, "the ring channel must not keep a backlog"
        publisher.undeclare()
    assert sub_session.is_closed() and pub_session.is_closed()
    with pytest.raises(RuntimeError, match="closed"):
        frames.try_recv()


def test_shared_memory_pool_holds_frames_and_larger_ones_arrive_over_the_link(port: int) -> None:
    """Frames that fit the publisher's pool arrive in shared memory (once Zenoh has created the pool, lazily, at the
    first large message); one larger than the whole pool is sent over the TCP link instead and arrives intact."""
    keys = Keys(robot="pool")
    assert json.loads(SessionConfig().to_zenoh_config().get_json(
        "transport/shared_memory/transport_optimization/pool_size")) == 4 * 2**20
    with pytest.raises(ValueError):
        SessionConfig(shm_pool_mib=0)
    listener = SessionConfig(listen=[f"tcp/127.0.0.1:{port}"])
    connector = SessionConfig(connect=[f"tcp/127.0.0.1:{port}"], shm_pool_mib=1.0)
    rng = np.random.default_rng(0)
    small = rng.integers(0, 256, 320 * 240, np.uint8).tobytes()  # 75 KiB: fits the 1 MiB pool
    large = rng.integers(0, 256, 3 * 2**20, np.uint8).tobytes()  # 3 MiB: cannot
    with open_session(listener) as sub_session, open_session(connector) as pub_session:
        received: list[tuple[bytes, bool]] = []
        subscriber = sub_session.declare_subscriber(
            keys.camera_image, lambda s: received.append((s.payload.to_bytes(), s.payload.as_shm() is not None)))
        publisher = declare_publisher(pub_session, keys, "camera_image")

        def put_and_receive(payload: bytes) -> tuple[bytes, bool]:
            """Put until it arrives (puts before the subscription has propagated are dropped)."""
            received.clear()
            deadline = time.monotonic() + 10.0
            while not received:
                assert time.monotonic() < deadline, f"a {len(payload)}-byte frame did not arrive within 10 s"
                publisher.put(payload)
                time.sleep(0.1)
            return received[0]

        deadline = time.monotonic() + 10.0
        while not put_and_receive(small)[1]:
            assert time.monotonic() < deadline, "no frame arrived in shared memory within 10 s"
        assert put_and_receive(large) == (large, False)
        assert put_and_receive(small) == (small, True)
        publisher.undeclare()
        subscriber.undeclare()

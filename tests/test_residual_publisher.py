"""`ResidualPublisher` over real Zenoh sessions on loopback: nothing is computed while nobody subscribes, images at
the reduced rate while someone does (32FC1, NaN as 0, the frame's header), nothing again once they leave."""

from __future__ import annotations

import threading
import time

import numpy as np
from conftest import free_port

from ddvs_service.protocol import Header, SessionConfig, Time, decode_image, open_session
from ddvs_service.service.residual_publisher import ResidualPublisher

KEY = "ddvs/residualtest/servo/residual"


def _offer_for(publisher: ResidualPublisher, seconds: float, computed: list[int]) -> int:
    """Offer a residual every 5 ms for `seconds`; returns how many were published."""
    def compute() -> np.ndarray:
        computed.append(1)
        image = np.full((3, 4), 2.5, np.float32)
        image[0, 0] = np.nan
        return image

    published, end = 0, time.monotonic() + seconds
    while time.monotonic() < end:
        published += publisher.offer(Header(Time.from_ns(7), "camera"), compute)
        time.sleep(0.005)
    return published


def _wait(condition, timeout: float = 5.0) -> bool:
    end = time.monotonic() + timeout
    while not condition() and time.monotonic() < end:
        time.sleep(0.02)
    return condition()


def test_residuals_only_while_watched_and_at_the_reduced_rate():
    port = free_port()
    computed: list[int] = []
    received: list[bytes] = []
    arrived = threading.Event()
    with open_session(SessionConfig(listen=[f"tcp/127.0.0.1:{port}"])) as service:
        zenoh_publisher = service.declare_publisher(KEY)
        publisher = ResidualPublisher(zenoh_publisher, rate_hz=10.0)
        assert _offer_for(publisher, 0.5, computed) == 0 and not computed  # nobody watching: nothing computed
        with open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"])) as viewer:
            def on_sample(sample) -> None:
                received.append(sample.payload.to_bytes())
                arrived.set()

            subscriber = viewer.declare_subscriber(KEY, on_sample)
            assert _wait(lambda: publisher.watched)
            published = _offer_for(publisher, 1.0, computed)
            assert 8 <= published <= 11 and len(computed) == published  # 10 Hz, not the 200 Hz offered
            assert arrived.wait(2.0)
            subscriber.undeclare()
            assert _wait(lambda: not publisher.watched)
            before = len(computed)
            assert _offer_for(publisher, 0.3, computed) == 0 and len(computed) == before
        publisher.close()
        zenoh_publisher.undeclare()
    image = decode_image(received[0])
    assert image.encoding == "32FC1" and image.header.stamp.to_ns() == 7
    expected = np.full((3, 4), 2.5, np.float32)
    expected[0, 0] = 0.0
    np.testing.assert_array_equal(image.array, expected)

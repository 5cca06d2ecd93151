"""Soak: 20,000 frames through `ddvs serve` — resident memory and latency stay flat after warm-up."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import psutil
import pytest
from conftest import free_port
from test_service_node import W, running_service, scene, service_config, shifted

FRAMES = 20_000
WARM_UP = 2_000


@pytest.mark.slow
def test_soak_memory_and_latency_stay_flat(tmp_path: Path) -> None:
    port = free_port()
    config = service_config(port, tmp_path / "state").model_copy(update={"status_every_frame": True})
    img = scene()
    frames = [shifted(img, 1.5 * np.cos(a), 1.5 * np.sin(a)) for a in np.linspace(0, 2 * np.pi, 60, endpoint=False)]
    with running_service(config, tmp_path, port) as (service, op):
        assert op.command(op="set_reference", source="next_frame").ok
        op.send(img)
        assert op.command(op="start").ok
        proc = psutil.Process(service.proc.pid)
        latency = np.empty(FRAMES)
        rss_after_warm_up = 0
        for k in range(FRAMES):
            status = op.send(frames[k % len(frames)])
            assert status["state"] == "SERVOING", status
            latency[k] = status["latency_ms"]["total"]
            if k == WARM_UP:
                rss_after_warm_up = proc.memory_info().rss
            op.statuses.clear()
            op.twists.clear()
        rss_end = proc.memory_info().rss
    growth = rss_end / rss_after_warm_up - 1.0
    early = float(np.median(latency[WARM_UP:WARM_UP + 2000]))
    late = float(np.median(latency[-2000:]))
    print(f"soak: {FRAMES} frames, RSS {rss_after_warm_up / 2**20:.1f} → {rss_end / 2**20:.1f} MiB "
          f"({growth:+.2%}), median latency {early:.2f} → {late:.2f} ms (frame width {W})")
    assert growth < 0.05
    assert late < 1.5 * early + 1.0

"""`ddvs ctl`: argument → `Command` mapping, and exit codes against a real `ddvs serve` process (0 ok, 1 refused,
2 no reply)."""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import free_port

from clients.ctl import EXIT_NO_REPLY, EXIT_OK, EXIT_REFUSED, add_arguments, command_from_args, dotted_patch

ROOT = Path(__file__).resolve().parents[1]


def _parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return parser.parse_args(list(argv))


def test_dotted_settings_become_a_nested_patch():
    patch = dotted_patch(["control.law=ddvs", "control.gains=[0.4,0.4,0.4,0.3,0.3,0.3]", "frame_timeout_s=0.5",
                          "registration.template_size=[70, 70]"])
    assert patch == {"control": {"law": "ddvs", "gains": [0.4, 0.4, 0.4, 0.3, 0.3, 0.3]}, "frame_timeout_s": 0.5,
                     "registration": {"template_size": [70, 70]}}
    with pytest.raises(ValueError, match=r"key\.path=value"):
        dotted_patch(["control.law"])
    with pytest.raises(ValueError, match="cannot also hold keys"):
        dotted_patch(["control=1", "control.law=ddvs"])


def test_actions_map_to_commands(tmp_path):
    image = np.random.default_rng(1).integers(0, 256, (48, 64), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "ref.png"), image)
    ref = str(tmp_path / "ref.png")
    cmd = command_from_args(_parse("set-reference", "--image", ref, "--roi", "4", "5", "30", "20"))
    assert cmd.op == "set_reference" and cmd.source == "upload"
    assert (cmd.roi.x, cmd.roi.y, cmd.roi.width, cmd.roi.height) == (4, 5, 30, 20)
    np.testing.assert_array_equal(cmd.image.to_array(), image)
    assert command_from_args(_parse("set-reference", "--next-frame")).source == "next_frame"
    assert command_from_args(_parse("state")).op == "get_state"
    assert command_from_args(_parse("config", "get")).op == "get_config"
    (tmp_path / "patch.json").write_text(json.dumps({"control": {"gains": 0.3}}))
    assert command_from_args(_parse("config", "set", "--file", str(tmp_path / "patch.json"))).config == {
        "control": {"gains": 0.3}}
    with pytest.raises(ValueError, match="cannot read reference image"):
        command_from_args(_parse("set-reference", "--image", str(tmp_path / "missing.png")))


def _ctl(port: int, *argv: str, timeout: float = 5.0) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "ddvs.cli", "ctl", "--timeout", str(timeout), "--robot", "ctltest",
           "--connect", f"tcp/127.0.0.1:{port}", *argv]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=60)


def test_no_service_exits_2():
    result = _ctl(free_port(), "state", timeout=0.5)
    assert result.returncode == EXIT_NO_REPLY, result.stderr
    assert "no reply" in result.stderr


@pytest.mark.slow
def test_exit_codes_against_a_running_service(tmp_path):
    port = free_port()
    serve = subprocess.Popen(
        [sys.executable, "-m", "ddvs.cli", "serve", "--fresh", "--state-dir", str(tmp_path / "state"),
         "--robot", "ctltest", "--listen", f"tcp/127.0.0.1:{port}"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        deadline = time.monotonic() + 60
        state = _ctl(port, "state", timeout=1.0)
        while state.returncode == EXIT_NO_REPLY and time.monotonic() < deadline:
            state = _ctl(port, "state", timeout=1.0)
        assert state.returncode == EXIT_OK, state.stdout + state.stderr
        assert json.loads(state.stdout)["data"]["state"] == "IDLE"
        refused = _ctl(port, "start")  # no reference yet
        assert refused.returncode == EXIT_REFUSED
        assert json.loads(refused.stdout)["ok"] is False
        changed = _ctl(port, "config", "set", "--set", "control.gains=0.3")
        assert changed.returncode == EXIT_OK, changed.stdout
        assert json.loads(_ctl(port, "config", "get").stdout)["data"]["control"]["gains"] == 0.3
        assert _ctl(port, "config", "set", "--set", "control.law=nonsense").returncode == EXIT_REFUSED
    finally:
        serve.send_signal(signal.SIGINT)
        try:
            serve.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            serve.kill()
            serve.communicate()

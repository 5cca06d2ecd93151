"""`ddvs demo` (`make demo`): the paper's real-data experiment on the simulated UR5, end to end, in real time.

Runs `orchestration.arm_run.run_arm` (sim, bridge and service as separate processes over Zenoh on loopback) with the
decoupled law (16)/(25), a 100×100 template (`DEMO_TEMPLATE`) and the sim's real-time clock (30 Hz) by default,
prints one progress line per second (state, error norm, images since start), and writes to `--out` (default
`reports/demo/`): the recording (a rosbag2 bag in MCAP storage, `recording/`), the figures of `ddvs plot`,
`summary.json` and `summary.md` (images to convergence beside the paper's 417 / 309, final pose error, latencies,
the bag's message counts and how to open it in Foxglove and replay it with ROS 2). It always ends: converged (then
settled for a few images) or at `--time-limit`; the child processes are stopped on every exit path, Ctrl-C
included. Exit status 0 when converged, 1 otherwise. `benchmarks/bench_demo_settling.py` runs it several times.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Literal

# Sec. 4 of the paper, real planar scene with a 70×70 template: images to convergence.
PAPER_IMAGES = {"dvs_reduced": 417, "dvs": 417, "ddvs": 309}
LAW_NAMES = {"dvs_reduced": "DVS (reduced error (13))", "dvs": "DVS", "ddvs": "decoupled DVS (16)"}
# The demo's template (issue 20): a 70×70 template sees the plane through ±4.8°, where a tilt of the estimate moves its
# corners by 0.01 px per 3e-3 of the control error. Near the goal its estimate of the decoupled error is off by 3–10e-3
# at a given pose (deterministic; as much on float frames and on frames blurred further: the rendered frames' small
# departures from a warped reference, not noise), so the servo settles where that biased estimate reads zero,
# 0.7–3 mm away. At 100×100 the same error is 1e-3 and the servo settles 0.1–0.3 mm away (docs/results/servoing.md).
DEMO_TEMPLATE = (100, 100)


def write_report(result: Any, settings: Any, out_dir: Path) -> dict[str, Any]:
    """Plots + `summary.json` + `summary.md` of one `ArmRunResult` into `out_dir`; returns the summary dict."""
    from clients.analysis import summarize
    from clients.bag import bag_counts, storage_files
    from clients.plot import plot_recording
    from clients.recording import load_recording

    recording = load_recording(result.recording_dir)
    bag = Path(result.recording_dir)
    title = f"{LAW_NAMES[settings.law]}, {settings.template[0]}×{settings.template[1]} template, {settings.clock}"
    figures = plot_recording(recording, out_dir / "plots", title)
    summary = {
        "law": settings.law, "template": list(settings.template), "clock": settings.clock, "fps": settings.fps,
        "scene": Path(settings.scene).name, "model": settings.model,
        "converged": result.converged, "end": result.reason, "wall_s": round(result.wall_s, 1),
        "paper_images_to_convergence": PAPER_IMAGES[settings.law],
        **summarize(recording).as_dict(),
        "figures": [str(p.relative_to(out_dir)) for p in figures],
        "recording": {"bag": str(bag), "files": [str(p) for p in storage_files(bag)], "messages": bag_counts(bag)},
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    (out_dir / "summary.md").write_text(summary_markdown(summary), encoding="utf-8")
    return summary


def _fmt(value: Any, spec: str) -> str:
    return "—" if value is None else format(value, spec)


def summary_markdown(s: dict[str, Any]) -> str:
    """The human-readable summary of `write_report`."""
    lat, p95 = s.get("latency_median_ms") or {}, s.get("latency_p95_ms") or {}
    lines = [
        f"# ddvs run: {LAW_NAMES[s['law']]}, {s['template'][0]}×{s['template'][1]} template, {s['clock']} clock",
        "",
        "| figure | value |",
        "|---|---|",
        f"| scene, registration model | {s.get('scene', '—')}, {s.get('model', 'planar')} |",
        f"| end | {s['end']} (wall {s['wall_s']} s) |",
        f"| images to convergence | {_fmt(s['images_to_convergence'], 'd')} "
        f"(paper: {s['paper_images_to_convergence']}) |",
        f"| final error norm | {_fmt(s['final_error_norm'], '.2e')} |",
        f"| initial pose error | {_fmt(s['initial_translation_error_mm'], '.1f')} mm, "
        f"{_fmt(s['initial_rotation_error_deg'], '.2f')}° |",
        f"| final pose error | {_fmt(s['final_translation_error_mm'], '.3f')} mm, "
        f"{_fmt(s['final_rotation_error_deg'], '.4f')}° |",
        "| service latency, median (p95) | " + ", ".join(
            f"{k} {lat[k]:.2f} ({p95[k]:.2f}) ms" for k in lat) + " |",
        f"| frame stamp → twist received, median | {_fmt(s['stamp_to_twist_ms'], '.1f')} ms |",
        "",
        "Figures: " + ", ".join(f"[{Path(f).name}]({f})" for f in s["figures"]),
        "",
        *recording_markdown(s["recording"]),
    ]
    return "\n".join(lines)


def recording_markdown(recording: dict[str, Any]) -> list[str]:
    """How to open the run's bag in Foxglove and replay it with ROS 2, and its message counts."""
    ros_file, json_file = recording["files"]
    return [
        f"## Recording: `{recording['bag']}` (rosbag2, MCAP storage; docs/recording.md)",
        "",
        "| topic | messages |",
        "|---|---|",
        *(f"| `{topic}` | {count} |" for topic, count in sorted(recording["messages"].items())),
        "",
        f"- Foxglove: *Open local file* and select both `{ros_file}` and `{json_file}`, then *Layouts → Import from "
        f"file* `{Path(recording['bag']).parent / 'foxglove-layout.json'}` (this run's topics: current image, "
        "reference, error norm, twist, state).",
        f"- ROS 2 (Jazzy or later, with `rosbag2_storage_mcap`): `ros2 bag info {recording['bag']}`, "
        f"`ros2 bag play {recording['bag']}` (the CDR topics: images, camera info, twist, joint states, reference).",
        f"- Python: `rosbags.highlevel.AnyReader([Path('{recording['bag']}')])`; `ddvs plot {recording['bag']}`.",
        "",
    ]


def scene_model(scene: Path) -> Literal["planar", "general"]:
    """The registration model a scene needs: "general" when the target the start looks at is a saddle (eq. (2)),
    else "planar"."""
    config = json.loads(scene.read_text(encoding="utf-8"))
    target = config["targets"][config.get("start", {}).get("target", 0)]
    return "general" if target["kind"] == "saddle" else "planar"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("reports/demo"), help="output folder (default reports/demo)")
    parser.add_argument("--law", choices=sorted(PAPER_IMAGES), default="ddvs", help="control law (default ddvs)")
    parser.add_argument("--clock", choices=["realtime", "lockstep"], default="realtime",
                        help="sim clock (default realtime, 30 Hz)")
    parser.add_argument("--template", type=int, nargs=2, default=DEMO_TEMPLATE, metavar=("W", "H"),
                        help="template size centred on the control point (default 100 100; the paper's 70 70 "
                             "settles on the estimate's tilt noise: docs/results/servoing.md)")
    parser.add_argument("--time-limit", type=float, default=240.0, help="seconds before giving up (default 240)")
    parser.add_argument("--scene", type=Path, help="arm scene (configs/arm/README.md; default the paper's poster, "
                                                   "configs/arm/ur5_poster.json); a saddle target is registered with "
                                                   "the general model of eq. (2)")


def run(args: argparse.Namespace) -> int:
    import shutil
    import signal

    from orchestration.arm_run import SCENE, ArmRunSettings, run_arm

    def on_sigterm(*_: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_sigterm)
    out: Path = args.out
    shutil.rmtree(out, ignore_errors=True)
    scene = args.scene or SCENE
    settings = ArmRunSettings(out_dir=out, law=args.law, template=tuple(args.template), clock=args.clock,
                              time_limit=args.time_limit, scene=scene, model=scene_model(scene))

    def progress(snap: dict[str, Any]) -> None:
        norm = snap["error_norm"]
        print(f"[demo] {snap['elapsed_s']:6.1f} s  {snap['state'] or '—':10s} error norm "
              f"{'—' if norm is None else f'{norm:.3e}'}  images {snap['images']:4d}  "
              f"frames {snap['rates_hz']['frames']:.0f} Hz  twists {snap['rates_hz']['twists']:.0f} Hz", flush=True)

    print(f"[demo] {LAW_NAMES[args.law]}, UR5 in SAPIEN, {args.clock} clock; starting sim, service and bridge …",
          flush=True)
    try:
        result = run_arm(settings, progress)
    except KeyboardInterrupt:
        print("[demo] interrupted; child processes stopped", flush=True)
        return 130
    summary = write_report(result, settings, out)
    print((out / "summary.md").read_text(encoding="utf-8"))
    print(f"[demo] {result.reason}; report in {out}/ (summary.md, summary.json, plots/)", flush=True)
    return 0 if summary["converged"] else 1

"""Figures of the speed and fleet results pages, drawn from the tables on those pages (`make docs`).

- `docs/results/speed.png`: one Gauss-Newton iteration of the registration against OpenCV's ECC and a float64
  numpy iteration, at each ROI size, from the table `benchmarks/bench_registration.py --write-readme` writes into
  `docs/results/speed.md` (its `registration-bench` section).
- `docs/results/fleet.png`: latency (median and p99) and memory against the number of robots at 30 Hz, one process
  serving them all against one process per robot, from the first table of `docs/results/fleet.md`.

A benchmark re-run that rewrites its table changes the figure at the next `make docs`.
"""

from __future__ import annotations

import re
from pathlib import Path

from scripts.docsgen.markdown import ROOT

RESULTS = ROOT / "docs" / "results"
_NUMBER = r"([\d,]+(?:\.\d+)?)"


def table_rows(text: str, first_header: str) -> list[list[str]]:
    """The body rows (cells stripped) of the first Markdown table whose header starts with `first_header`."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first_header}"))
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip().strip("|").split("|")])
    return rows


def _number(text: str) -> float:
    return float(text.replace(",", ""))


def registration_speed(page: Path = RESULTS / "speed.md") -> dict[str, dict[str, float]]:
    """ROI label → {ours, ECC, numpy} milliseconds per iteration, from the registration-bench section."""
    text = page.read_text(encoding="utf-8")
    section = text[text.index("<!-- registration-bench:begin -->"):text.index("<!-- registration-bench:end -->")]
    out = {}
    for cells in table_rows(section, "measurement | ours"):
        roi = re.search(r"(\d+×\d+) ROI", cells[0])
        if roi is None:
            continue
        out[roi.group(1)] = {name: _number(re.match(_NUMBER, cell).group(1))  # type: ignore[union-attr]
                             for name, cell in zip(("ours", "ECC", "numpy"), cells[1:4])}
    return out


def fleet_scaling(page: Path = RESULTS / "fleet.md") -> list[dict[str, float]]:
    """Per robot count: median and p99 latency (ms) and RSS (MB), one process and one process per robot."""
    rows = []
    for cells in table_rows(page.read_text(encoding="utf-8"), "robots at 30 Hz"):
        row: dict[str, float] = {"robots": _number(cells[0])}
        for mode, latency, memory in (("shared", cells[1], cells[2]), ("separate", cells[3], cells[4])):
            median, p99 = re.search(rf"{_NUMBER} / {_NUMBER}", latency).groups()  # type: ignore[union-attr]
            row[f"{mode}_median_ms"], row[f"{mode}_p99_ms"] = _number(median), _number(p99)
            row[f"{mode}_rss_mb"] = _number(re.search(rf"{_NUMBER} MB", memory).group(1))  # type: ignore[union-attr]
        rows.append(row)
    return rows


def draw(out_dir: Path = RESULTS) -> list[Path]:
    """Draw both figures into `out_dir`; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    speed = registration_speed()
    fig, ax = plt.subplots(figsize=(7, 3.4))
    width = 0.25
    for k, name in enumerate(("ours", "ECC", "numpy")):
        xs = [i + (k - 1) * width for i in range(len(speed))]
        ax.bar(xs, [speed[roi][name] for roi in speed], width, label=name)
    ax.set_xticks(range(len(speed)), [f"{roi} ROI" for roi in speed])
    ax.set_yscale("log")
    ax.set_ylabel("one Gauss-Newton iteration (ms)")
    ax.set_title("registration: ours against OpenCV's ECC and float64 numpy", fontsize=10)
    ax.grid(True, axis="y", which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    written = [out_dir / "speed.png"]
    fig.savefig(written[0], dpi=100, metadata={"Software": None})
    plt.close(fig)

    fleet = fleet_scaling()
    robots = [row["robots"] for row in fleet]
    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(10, 3.6))
    for mode, label in (("shared", "one process"), ("separate", "one process per robot")):
        line = ax_t.plot(robots, [row[f"{mode}_p99_ms"] for row in fleet], marker="o", label=f"{label}, p99")[0]
        ax_t.plot(robots, [row[f"{mode}_median_ms"] for row in fleet], ls="--", color=line.get_color(),
                  label=f"{label}, median")
        ax_m.plot(robots, [row[f"{mode}_rss_mb"] for row in fleet], marker="o", label=label)
    for ax in (ax_t, ax_m):
        ax.set_xscale("log", base=2)
        ax.set_xticks(robots, [str(int(n)) for n in robots])
        ax.set_xlabel("robots at 30 Hz")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    ax_t.set_ylabel("frame → twist latency (ms)")
    ax_m.set_ylabel("resident memory (MB)")
    fig.tight_layout()
    written.append(out_dir / "fleet.png")
    fig.savefig(written[1], dpi=100, metadata={"Software": None})
    plt.close(fig)
    return written

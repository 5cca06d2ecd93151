"""The status line of a run of trials on stderr: trials finished of the total, failures so far, elapsed time and an
estimate of the time left (the mean time per finished trial so far times the trials left, so it assumes the trials
still to come take as long on average as those done)."""

from __future__ import annotations

import sys
import time
from typing import TextIO


def status_line(finished: int, failed: int, total: int, elapsed_s: float) -> str:
    """`[finished/total] N failed, elapsed M:SS, left M:SS` (`left ?` before the first trial ends); `finished`
    counts the failed trials too."""
    left = "?" if finished == 0 else _clock(elapsed_s / finished * (total - finished))
    return f"[{finished}/{total}] {failed} failed, elapsed {_clock(elapsed_s)}, left {left}"


def _clock(seconds: float) -> str:
    """`H:MM:SS` from one hour on, else `M:SS`."""
    minutes, s = divmod(round(seconds), 60)
    hours, m = divmod(minutes, 60)
    return f"{hours}:{m:02d}:{s:02d}" if hours else f"{m}:{s:02d}"


class Progress:
    """The status line of `total` trials on `stream`: redrawn in place on a terminal, one line per update
    otherwise (a log file)."""

    def __init__(self, total: int, stream: TextIO = sys.stderr) -> None:
        self.total, self.stream = total, stream
        self.finished = self.failed = 0
        self.start = time.monotonic()
        self.live = stream.isatty()

    def update(self, failed: bool) -> None:
        """One more trial ended (`failed`: without a record)."""
        self.finished += 1
        self.failed += int(failed)
        line = status_line(self.finished, self.failed, self.total, time.monotonic() - self.start)
        end = "\n" if not self.live or self.finished == self.total else ""
        self.stream.write(("\r\x1b[K" if self.live else "") + line + end)
        self.stream.flush()

    def close(self) -> None:
        """End the line in place (an interrupted run on a terminal)."""
        if self.live and 0 < self.finished < self.total:
            self.stream.write("\n")
            self.stream.flush()

"""Continuity of the control error: the service acts only on an error consistent with the last trusted one.

Between two processed frames the camera moves by at most one or two periods of the saturated twist, so the control
error ε of eq. (7)/(13)/(16) changes by a few hundredths (at 30 Hz, 0.25 m/s at 0.7 m and 0.8 rad/s: about 0.03);
while the servo is LOST the camera holds still and ε does not change at all. A tracked frame whose error lies
farther than `jump_abs + jump_rel ‖ε_trusted‖` from the last trusted error comes from a different (wrong) fit: it is
reported as suspect and the service treats it as a lost frame (zero twist, re-acquisition). A genuine jump — the
camera moved by hand while the servo was LOST — is adopted once `rebase_frames` consecutive tracked frames agree
with each other (each within `jump_abs` of the one before: the camera holds still meanwhile), which a wrong fit
wandering with the image noise does not do for long. The service applies it only while the servo is active
(SERVOING, CONVERGED, LOST): the first frame after a start is trusted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass
class ErrorGuard:
    """The last trusted control error and the run of consistent suspect errors (module docstring)."""

    jump_abs: float = 0.1
    jump_rel: float = 0.25
    rebase_frames: int = 30
    _trusted: F64 | None = None
    _run: list[F64] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not (self.jump_abs > 0.0 and self.jump_rel >= 0.0 and self.rebase_frames >= 1):
            raise ValueError(f"need jump_abs > 0, jump_rel ≥ 0, rebase_frames ≥ 1, got {self.jump_abs}, "
                             f"{self.jump_rel}, {self.rebase_frames}")

    def reset(self) -> None:
        """Forget the trusted error (a new reference: the first tracked frame is trusted)."""
        self._trusted, self._run = None, []

    def _near(self, error: F64, anchor: F64) -> bool:
        return _norm(error - anchor) <= self.jump_abs + self.jump_rel * _norm(anchor)

    def check(self, error: F64) -> str:
        """Why `error` (of a tracked frame) is not to be acted on ("" when it is; it then becomes the trusted one)."""
        error = np.asarray(error, dtype=np.float64)
        if self._trusted is None or self._near(error, self._trusted):
            self._trusted, self._run = error, []
            return ""
        agrees = bool(self._run) and _norm(error - self._run[-1]) <= self.jump_abs
        self._run = [*self._run, error] if agrees else [error]
        if len(self._run) >= self.rebase_frames:
            self._trusted, self._run = error, []
            return ""
        jump = float(np.linalg.norm(error - self._trusted))
        return (f"suspect fit: the control error jumped by {jump:.3g} from the last trusted one (norm "
                f"{np.linalg.norm(self._trusted):.3g}; at most {self.jump_abs:g} + {self.jump_rel:g}× its norm "
                f"between frames); {len(self._run)}/{self.rebase_frames} consistent frames to adopt it")


def _norm(v: F64) -> float:
    """‖v‖ as `np.linalg.norm` computes it (√(v·v)), without its wrapper: the guard runs on every frame."""
    return math.sqrt(v.dot(v))

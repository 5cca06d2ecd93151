"""Structured log lines for every ddvs node (headless deployment): one JSON object per line on stderr.

Each line has `ts` (Unix seconds), `level`, `logger`, `msg` and any keyword fields passed as `extra={"fields": {...}}`.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from typing import Any


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        line: dict[str, Any] = {
            "ts": round(record.created, 6),
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        line.update(getattr(record, "fields", {}))
        if record.exc_info:
            line["exc"] = self.formatException(record.exc_info)
        return json.dumps(line, default=str)


def setup_logging(level: str = "INFO") -> None:
    """Route every `logging` record to stderr as one JSON line (idempotent)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    logging.Formatter.converter = time.gmtime


def fields(**kwargs: Any) -> dict[str, Any]:
    """`extra=` argument carrying structured fields: `log.info("msg", extra=fields(state="LOST"))`."""
    return {"fields": kwargs}

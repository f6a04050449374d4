"""Structured log lines, one per record, with the drone id: ``key=value`` pairs or JSON.

journald keeps each line as one entry; ``journalctl -u swarm-onboard@3 | grep event=transition``
or ``jq`` on the JSON form finds what happened. Use ``event(log, "name", key=value, ...)``.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time
from typing import Any, TextIO

_FIELDS = "swarm_fields"


def _kv_value(v: Any) -> str:
    if isinstance(v, float):
        s = f"{v:.4g}" if math.isfinite(v) else "null"
    elif isinstance(v, (list, tuple)):
        s = ",".join(_kv_value(x) for x in v)
    else:
        s = str(v)
    if s == "" or any(c in s for c in ' "=\n\t'):
        return json.dumps(s)
    return s


class KvFormatter(logging.Formatter):
    """``ts=2024-..Z level=info drone=3 event=transition source=hover target=landing``."""

    def __init__(self, drone_id: int) -> None:
        super().__init__()
        self.drone_id = drone_id

    def format(self, record: logging.LogRecord) -> str:
        ts = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
        parts = [
            f"ts={ts}.{int(record.msecs):03d}Z",
            f"level={record.levelname.lower()}",
            f"drone={self.drone_id}",
            f"logger={record.name}",
            f"event={_kv_value(record.getMessage())}",
        ]
        for k, v in getattr(record, _FIELDS, {}).items():
            parts.append(f"{k}={_kv_value(v)}")
        if record.exc_info:
            parts.append(f"exc={_kv_value(self.formatException(record.exc_info))}")
        return " ".join(parts)


class JsonFormatter(logging.Formatter):
    """One JSON object per line with the same keys as ``KvFormatter``."""

    def __init__(self, drone_id: int) -> None:
        super().__init__()
        self.drone_id = drone_id

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "ts": record.created,
            "level": record.levelname.lower(),
            "drone": self.drone_id,
            "logger": record.name,
            "event": record.getMessage(),
        }
        for k, v in getattr(record, _FIELDS, {}).items():
            out[k] = v if not (isinstance(v, float) and not math.isfinite(v)) else None
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


def setup_logging(
    drone_id: int, level: str = "info", fmt: str = "kv", stream: TextIO | None = None
) -> logging.Handler:
    """Route every logger to ``stream`` (stderr: journald) in the chosen format."""
    handler = logging.StreamHandler(stream if stream is not None else sys.stderr)
    handler.setFormatter(JsonFormatter(drone_id) if fmt == "json" else KvFormatter(drone_id))
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(getattr(logging, level.upper()))
    return handler


def event(log: logging.Logger, name: str, level: int = logging.INFO, **fields: Any) -> None:
    """Log the event ``name`` with structured fields."""
    log.log(level, name, extra={_FIELDS: fields})

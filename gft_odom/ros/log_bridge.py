"""Python `logging` of the package -> the node's ROS logger (rosout, --log-level), throttled.

The core logs with `logging` (it never imports rclpy); without this its warnings went to bare
stderr once per scan, missed /rosout and ignored `--log-level`.
"""

from __future__ import annotations

import logging
import time

from rclpy.logging import LoggingSeverity


class RosLogHandler(logging.Handler):
    """Forwards records; the same message template is logged at most once per `period_s`."""

    def __init__(self, ros_logger, period_s: float) -> None:
        super().__init__(logging.DEBUG)
        self._ros_logger = ros_logger
        self._period_s = period_s
        self._last_s: dict[tuple[str, str], float] = {}
        self._suppressed: dict[tuple[str, str], int] = {}

    def emit(self, record: logging.LogRecord) -> None:
        """Forward one Python log record to the node logger (throttled)."""
        key = (record.name, str(record.msg))
        now_s = time.monotonic()
        last_s = self._last_s.get(key)
        if last_s is not None and now_s - last_s < self._period_s:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        self._last_s[key] = now_s
        try:
            text = f'{record.name}: {record.getMessage()}'
        except Exception:  # a bad format string must not break the callback
            text = f'{record.name}: {record.msg!r} {record.args!r}'
        skipped = self._suppressed.pop(key, 0)
        if skipped:
            text += f' ({skipped} more like it in the last {self._period_s:.0f} s)'
        if record.levelno >= logging.ERROR:
            self._ros_logger.error(text)
        elif record.levelno >= logging.WARNING:
            self._ros_logger.warning(text)
        elif record.levelno >= logging.INFO:
            self._ros_logger.info(text)
        else:
            self._ros_logger.debug(text)


def forward_python_logging(ros_logger, period_s: float,
                           name: str = 'gft_odom') -> RosLogHandler:
    """Route logger `name` to `ros_logger` at its severity; returns the handler (to remove)."""
    severity = LoggingSeverity(ros_logger.get_effective_level())
    level = {LoggingSeverity.UNSET: logging.INFO, LoggingSeverity.DEBUG: logging.DEBUG,
             LoggingSeverity.INFO: logging.INFO, LoggingSeverity.WARN: logging.WARNING,
             LoggingSeverity.ERROR: logging.ERROR,
             LoggingSeverity.FATAL: logging.CRITICAL}[severity]
    handler = RosLogHandler(ros_logger, period_s)
    logger = logging.getLogger(name)
    # With nodes in one process, the state before the first is what the last one restores.
    forwarding = [h for h in logger.handlers if isinstance(h, RosLogHandler)]
    handler.restore = (forwarding[0].restore if forwarding
                       else (logger, logger.level, logger.propagate))
    logger.addHandler(handler)
    logger.setLevel(level)
    logger.propagate = False
    return handler


def stop_forwarding(handler: RosLogHandler) -> None:
    """Undo `forward_python_logging` (the node is destroyed; others may log in this process)."""
    logger, level, propagate = handler.restore
    logger.removeHandler(handler)
    if not any(isinstance(h, RosLogHandler) for h in logger.handlers):
        logger.setLevel(level)
        logger.propagate = propagate

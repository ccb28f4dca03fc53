"""The ``[log]`` section of the configuration: where flight logs go and what they hold."""

from __future__ import annotations

from ahrs_service.core.settings import Section, boolean, directory, number

LOG: Section = {
    "enabled": (True, boolean),
    "directory": ("flight-logs", directory),
    "rotate_mb": (0.0, number(0.0, 1_000_000.0)),  # 0 = no size rotation; at most 1 TB
    "rotate_minutes": (0.0, number(0.0, 525_600.0)),  # 0 = no time rotation; at most a year
    # the estimator's diagnostics (rest, rejections, form) in /attitude this often, Hz
    "diagnostics_hz": (10.0, number(0.0, 1000.0)),
    # samples faster than this are logged one message per FIFO burst (/imu/raw_block,
    # /attitude_block) instead of one per sample, Hz; 0: always (docs/logs.md)
    "block_messages_above_hz": (1500.0, number(0.0, 1_000_000.0)),
    # the simulator's ground truth (/attitude/truth) when the source has one: false logs
    # what a real sensor's log holds (raw + estimate)
    "truth": (True, boolean),
}

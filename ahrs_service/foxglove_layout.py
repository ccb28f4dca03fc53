"""The shipped Foxglove layout: one layout for the live view and for MCAP logs.

``ahrs-service foxglove-layout > layout.json`` prints it; the same file ships in the package
(``ahrs_service/foxglove_layout.json``, written by ``python -m ahrs_service.foxglove_layout``
and checked against :func:`layout` by the tests). The JSON is the ``foxglove-sdk`` layout format (version
1, a tree of split containers and panels), built here from plain dicts so printing it needs
no extra; tests/test_foxglove_layout.py builds the same layout with ``foxglove.layouts`` and
checks that every topic and field it names is one the service writes.

Panels: a 3-D view of frame ``body`` in frame ``ned`` (/tf), the Log panel (/log); plots of
roll/pitch/yaw (estimate and, where the log has it, truth), raw gyro, accelerometer and
magnetometer (/imu/raw, body FRD), loop timing and lost samples (/loop), and the estimator's
rejection flags (/attitude diagnostics, written at ``log.diagnostics_hz``).
"""

from __future__ import annotations

import json
from importlib import resources
from typing import Any

SHIPPED = "foxglove_layout.json"

_AXES = ("x", "y", "z")


def _series(path: str, label: str, **extra: Any) -> dict[str, Any]:
    return {"value": path, "label": label, "enabled": True, "timestampMethod": "receiveTime", **extra}


def _panel(panel_type: str, config: dict[str, Any], title: str | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"type": "panel", "panelType": panel_type, "config": config}
    if title is not None:
        out["title"] = title
    out["version"] = 1
    return out


def _plot(title: str, series: list[dict[str, Any]], y_label: str) -> dict[str, Any]:
    return _panel("Plot", {"paths": series, "showLegend": True, "yAxisLabel": y_label}, title)


def _split(direction: str, *items: tuple[float, dict[str, Any]]) -> dict[str, Any]:
    return {"type": "split", "direction": direction,
            "items": [{"proportion": p, "content": c} for p, c in items]}


#: (plot title, y label, [(message path, legend label)]): every plotted field, in panel order
PLOTS: list[tuple[str, str, list[tuple[str, str]]]] = [
    ("Attitude", "rad", [("/attitude.roll", "roll"), ("/attitude.pitch", "pitch"), ("/attitude.yaw", "yaw"),
                         ("/attitude/truth.roll", "truth roll"), ("/attitude/truth.pitch", "truth pitch"),
                         ("/attitude/truth.yaw", "truth yaw")]),
    ("Gyro (body FRD)", "rad/s", [(f"/imu/raw.gyr[{i}]", a) for i, a in enumerate(_AXES)]),
    ("Accelerometer (body FRD)", "m/s²", [(f"/imu/raw.acc[{i}]", a) for i, a in enumerate(_AXES)]),
    ("Magnetometer (body FRD)", "µT", [(f"/imu/raw.mag[{i}]", a) for i, a in enumerate(_AXES)]),
    ("Loop timing", "µs", [("/loop.period_jitter_p99_us", "jitter p99"), ("/loop.lateness_p99_us", "lateness p99"),
                           ("/loop.period_jitter_max_us", "jitter max")]),
    ("Lost samples and overruns", "count", [("/loop.source.lost.total", "lost samples"),
                                            ("/loop.missed_ticks", "missed ticks"),
                                            ("/loop.overruns", "overruns"),
                                            ("/loop.source.bus_errors", "bus errors")]),
    ("Rejections", "flag / count", [("/attitude.diagnostics.mag_disturbed", "mag rejected"),
                                    ("/attitude.diagnostics.rest", "at rest"),
                                    ("/attitude.diagnostics.reduced", "reduced form"),
                                    ("/attitude.diagnostics.acc_skipped", "acc skipped"),
                                    ("/attitude.diagnostics.mag_skipped", "mag skipped")]),
]

THREE_D = {"followTf": "ned", "followMode": "follow-none"}
LOG = {"topicToRender": "/log", "showLevel": True, "showTime": True}


def _plot_panel(title: str, y_label: str, paths: list[tuple[str, str]]) -> dict[str, Any]:
    dashed = {"lineStyle": "dashed"}
    return _plot(title, [_series(p, label, **(dashed if p.startswith("/attitude/truth") else {}))
                         for p, label in paths], y_label)


def layout() -> dict[str, Any]:
    """The layout as a JSON-ready dict (foxglove-sdk layout format, version 1)."""
    plots = [_plot_panel(*p) for p in PLOTS]
    left = _split("column", (2.0, _panel("ThreeDee", THREE_D, "Body in NED")), (1.0, _panel("Log", LOG, "Health (/log)")))
    middle = _split("column", *((1.0, p) for p in plots[:4]))
    right = _split("column", *((1.0, p) for p in plots[4:]))
    return {"version": 1, "content": _split("row", (1.0, left), (1.2, middle), (1.0, right))}


def layout_json() -> str:
    """The layout as the JSON text that is shipped and printed."""
    return json.dumps(layout(), indent=2, ensure_ascii=False) + "\n"


def shipped_layout_json() -> str:
    """The layout file installed with the package."""
    return resources.files("ahrs_service").joinpath(SHIPPED).read_text(encoding="utf-8")


def message_paths() -> list[str]:
    """Every message path a panel names (topic + field), for the test against a real log."""
    return [p for _, _, paths in PLOTS for p, _ in paths]


def topics() -> list[str]:
    """Every topic the layout reads."""
    return sorted({p.split(".", 1)[0] for p in message_paths()} | {"/tf", "/log"})


if __name__ == "__main__":  # regenerate the shipped file: python -m ahrs_service.foxglove_layout
    from pathlib import Path

    Path(__file__).with_name(SHIPPED).write_text(layout_json(), encoding="utf-8")

"""The shipped Foxglove layout: valid foxglove-sdk layout JSON, and every topic and field it
names is one the service writes (checked against the MCAP of a real short run)."""

from __future__ import annotations

import json
import re
import socket

import pytest

from ahrs_service import foxglove_layout
from ahrs_service.cli import main
from ahrs_service.logs.reader import MessageSource
from ahrs_service.logs.schemas import decode
from ahrs_service.service import Service
from tests.test_service import service_config

pytestmark = pytest.mark.timeout(120)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


_STEP = re.compile(r"\.(\w+)|\[(\d+)\]")


def resolve(message, path: str):
    """The value at ``path`` (".a.b[0]") in a decoded message; KeyError/IndexError if absent."""
    value = message
    for key, index in _STEP.findall(path):
        value = value[key] if key else value[int(index)]
    return value


def test_cli_prints_the_shipped_file_and_it_is_the_generated_layout(capsys):
    assert main(["foxglove-layout"]) == 0
    printed = capsys.readouterr().out
    assert printed == foxglove_layout.shipped_layout_json() == foxglove_layout.layout_json()


def test_layout_is_what_the_foxglove_sdk_builds():
    fl = pytest.importorskip("foxglove.layouts")

    def plot(title, y_label, paths):
        return fl.PlotPanel(title=title, config=fl.PlotConfig(show_legend=True, y_axis_label=y_label, paths=[
            fl.PlotSeries(value=p, label=label, enabled=True, timestamp_method="receiveTime",
                          **({"line_style": "dashed"} if p.startswith("/attitude/truth") else {}))
            for p, label in paths]))

    def column(*items):
        return fl.SplitContainer(direction="column", items=[fl.SplitItem(proportion=p, content=c) for p, c in items])

    plots = [plot(*p) for p in foxglove_layout.PLOTS]
    left = column((2.0, fl.ThreeDeePanel(title="Body in NED", config=fl.ThreeDeeConfig(follow_tf="ned", follow_mode="follow-none"))),
                  (1.0, fl.LogPanel(title="Health (/log)", config=fl.LogConfig(topic_to_render="/log", show_level=True, show_time=True))))
    sdk = fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=1.0, content=left),
        fl.SplitItem(proportion=1.2, content=column(*((1.0, p) for p in plots[:4]))),
        fl.SplitItem(proportion=1.0, content=column(*((1.0, p) for p in plots[4:]))),
    ]))
    assert json.loads(sdk.to_json()) == foxglove_layout.layout()


def test_every_topic_and_field_of_the_layout_is_in_a_real_log(tmp_path):
    # robust estimator (the default: it has rejection diagnostics), simulated board with truth
    svc = Service(service_config(tmp_path, free_port(), source={"profile": "figure8"}), duration_s=1.5)
    svc.start()
    try:
        name, value = next(iter(svc.estimator.get_params().items()))
        svc.set_estimator_param(name, value)  # a parameter change: the /log panel has an event
        svc.run()
    finally:
        svc.close()
    (path,) = (tmp_path / "logs").glob("*.mcap")
    by_topic: dict[str, list] = {}
    for topic, _, _, data in MessageSource(path):
        by_topic.setdefault(topic, []).append(decode(data))
    missing_topics = [t for t in foxglove_layout.topics() if not by_topic.get(t)]
    assert missing_topics == []
    unresolved = []
    for full in foxglove_layout.message_paths():
        topic = max((t for t in by_topic if full.startswith(t + ".") or full.startswith(t + "[")), key=len)
        field = full[len(topic):]
        values = []
        for msg in by_topic[topic]:
            try:
                values.append(resolve(msg, field))
            except (KeyError, IndexError, TypeError):
                pass
        if not any(isinstance(v, (int, float)) for v in values):  # bool is an int: flags plot as 0/1
            unresolved.append(full)
    assert unresolved == []

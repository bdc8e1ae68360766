"""The Foxglove / Lichtblick layout committed in the repository (layouts/mecanum_drive.json):
valid JSON in the layout format (every panel the tree names is configured, every configured
panel is in the tree), and every topic and message path it names is one a run publishes:
checked against a simulated run's MCAP (the `mcap` package reads the records, `rosbags`
decodes the CDR), each plot path resolved to a number on the logged messages.
"""

from __future__ import annotations

import json
import pathlib
import re
import subprocess
from collections.abc import Iterator
from typing import Any

import pytest
from mcap.reader import make_reader
from test_hostsim_log import typestore_for

ROOT = pathlib.Path(__file__).resolve().parent.parent
LAYOUT = ROOT / "layouts" / "mecanum_drive.json"

#: Topics only `mecanum-runner` logs (docs: README, "Logs"): a layout may name them too.
RUNNER_ONLY = {"/firmware/steps"}

#: A message path: the topic, then fields and indexes (`/joint_states.velocity[0]`).
PATH = re.compile(r"^(/[A-Za-z0-9_/]+?)((?:\.[A-Za-z_][A-Za-z0-9_]*|\[\d+\])*)$")


def panels(node: Any) -> Iterator[str]:
    """The panel ids of a layout tree (a panel id, or a split of two subtrees)."""
    if isinstance(node, str):
        yield node
    elif isinstance(node, dict):
        yield from panels(node["first"])
        yield from panels(node["second"])
    else:
        raise AssertionError(f"not a layout node: {node!r}")


def named_paths(config: dict[str, Any]) -> Iterator[tuple[str, str]]:
    """(panel id, message path or topic) for every topic a panel's configuration names."""
    for panel_id, cfg in config.items():
        for topic in cfg.get("topics", {}):
            yield panel_id, topic
        for key in ("topicToRender", "topicPath"):
            if key in cfg:
                yield panel_id, cfg[key]
        for path in cfg.get("paths", []):
            yield panel_id, path["value"]


@pytest.fixture(scope="module")
def layout() -> dict[str, Any]:
    return json.loads(LAYOUT.read_text())


@pytest.fixture(scope="module")
def square_log(hostsim_bin: pathlib.Path, tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    out = tmp_path_factory.mktemp("layout")
    proc = subprocess.run([str(hostsim_bin), "run", "square", "--out", str(out), "--no-plot"],
                          capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr
    return out / "square.mcap"


def test_the_layout_is_a_layout_whose_tree_and_panels_agree(layout) -> None:
    assert set(layout) >= {"configById", "layout", "globalVariables", "userNodes", "playbackConfig"}
    config = layout["configById"]
    in_tree = set(panels(layout["layout"]))
    for panel_id in list(in_tree):
        for tab in config.get(panel_id, {}).get("tabs", []):
            in_tree |= set(panels(tab["layout"]))
    assert in_tree == set(config), (in_tree ^ set(config))
    kinds = {panel_id.split("!", 1)[0] for panel_id in config}
    # The panels: odometry against ground truth in 3D, plots of the wheel speeds and
    # currents, the diagnostics, the CAN frames.
    assert {"3D", "Plot", "DiagnosticSummary", "DiagnosticStatusPanel", "RawMessages"} <= kinds
    # The robot's parameters, where the source declares them (the ROS 2 bridge's `robot.*`
    # through foxglove_bridge; docs/protocol.md, "Parameters").
    assert "Parameters" in kinds
    three_d = config["3D!odometry"]["topics"]
    assert {"/odom", "/ground_truth/odom"} <= set(three_d)
    plotted = {p["value"] for cfg in config.values() for p in cfg.get("paths", [])}
    assert {f"/joint_states.velocity[{i}]" for i in range(4)} <= plotted
    assert {f"/joint_states.effort[{i}]" for i in range(4)} <= plotted
    assert {cfg.get("topicPath") for cfg in config.values()} >= {"/can/rx", "/can/tx"}


def test_every_topic_and_path_the_layout_names_is_published(layout, square_log) -> None:
    with open(square_log, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic for c in summary.channels.values()}
        store = typestore_for(summary.schemas.values())
        first: dict[str, Any] = {}
        for schema, channel, message in reader.iter_messages():
            if channel.topic not in first:
                first[channel.topic] = store.deserialize_cdr(message.data, schema.name)
    checked = 0
    for panel_id, path in named_paths(layout["configById"]):
        m = PATH.match(path)
        assert m, f"{panel_id}: {path!r} is not a message path"
        topic, fields = m.group(1), m.group(2)
        if topic in RUNNER_ONLY:
            continue
        assert topic in topics, f"{panel_id}: {topic} is not among the run's topics {sorted(topics)}"
        value = first[topic]
        for part in re.findall(r"\.([A-Za-z_][A-Za-z0-9_]*)|\[(\d+)\]", fields):
            name, index = part
            value = getattr(value, name) if name else value[int(index)]
        if panel_id.startswith("Plot!"):
            assert isinstance(value, (int, float)), f"{panel_id}: {path} is {value!r}, not a number"
        checked += 1
    assert checked >= 20, checked

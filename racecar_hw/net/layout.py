"""The shipped Foxglove layout, built with the SDK's ``foxglove.layouts``, and its Lichtblick twin.

``python -m racecar_hw.net.layout [DIR]`` writes ``racecar.json`` (Foxglove's layout format, import it
with Layouts > Import) and ``racecar-lichtblick.json`` (the same panels in the older layout format
Lichtblick imports) into ``DIR`` (default: the package's ``config/foxglove``). The tests check the
shipped files are what this module builds.

Panels: a 3D view following base_link (scan, safety scene, map and true pose in the simulator);
plots of the commanded, output, allowed and measured speed and of the steering; the mux's active
source over time; diagnostics (mux and safety) and logs; Teleop (10 Hz on ``/foxglove/cmd_vel``) and
E-STOP / release service buttons.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import foxglove.layouts as fl

from racecar_hw.base.topics import FOXGLOVE_TELEOP_TOPIC, MUX_ACTIVE_TOPIC
from racecar_hw.net.foxglove_server import LOG_TOPIC, SCENE_TOPIC, SERVICE_PREFIX, SPEEDS_TOPIC

TELEOP_RATE_HZ = 10.0
FILES = ("racecar.json", "racecar-lichtblick.json")
#: Panel type names that differ in the older layout format (Lichtblick, Foxglove Studio 1.x).
LEGACY_PANEL_TYPES = {"ThreeDee": "3D", "DiagnosticsSummary": "DiagnosticSummary",
                      "DiagnosticsDetail": "DiagnosticStatusPanel", "Log": "RosOut",
                      "ServiceCall": "CallService"}


def _speed(field: str, label: str, colour: str, style: str = "solid") -> fl.PlotSeries:
    return fl.PlotSeries(value=f"{SPEEDS_TOPIC}.{field}", label=label, color=colour, line_style=style,
                         timestamp_method="receiveTime", enabled=True)


def build_layout(teleop_speed_mps: float = 0.5, teleop_yaw_rate: float = 1.0) -> fl.Layout:
    """The racecar-hw layout."""
    three_d = fl.ThreeDeePanel(title="car", config=fl.ThreeDeeConfig(
        follow_tf="base_link", follow_mode="follow-position",
        # 8 m away, looking down at 35 degrees: the car, its swept band and the nearest walls fill the view
        camera_state=fl.ThreeDeeCameraState(distance=8.0, phi=35.0, theta_offset=0.0, perspective=True),
        scene=fl.BaseRendererSceneSettings(transforms=fl.BaseRendererTransforms(show_label=False)),
        topics={
            # a colour field must be named, or the viewer replaces the flat colour by a colour map
            "/scan": fl.BaseRendererLaserScanTopicSettings(visible=True, point_size=4.0, color_mode="flat",
                                                           flat_color="#1f9bde", color_field="range"),
            SCENE_TOPIC: fl.BaseRendererSceneUpdateTopicSettings(visible=True),
            "/map": fl.BaseRendererRosOccupancyGridTopicSettings(visible=True, color_mode="map", alpha=0.6),
            "/sim/pose": fl.BaseRendererPoseTopicSettings(visible=True, type="arrow", color="#ff40ff"),
        }))
    speeds = fl.PlotPanel(title="speed (m/s)", config=fl.PlotConfig(paths=[
        _speed("commanded", "commanded", "#1f77b4"), _speed("output", "output", "#17becf", "dashed"),
        _speed("allowed", "allowed", "#f59600"), _speed("measured", "measured", "#2ca02c")],
        show_legend=True, time_window_mode="sliding", following_view_width=20.0))
    steering = fl.PlotPanel(title="steering (rad)", config=fl.PlotConfig(paths=[
        _speed("steering", "steering", "#9467bd")], time_window_mode="sliding", following_view_width=20.0))
    source = fl.StateTransitionsPanel(title="active source", config=fl.StateTransitionsConfig(
        paths=[fl.StateTransitionsSeries(value=f"{MUX_ACTIVE_TOPIC}.data", label="mux",
                                         timestamp_method="receiveTime", enabled=True)]))
    diagnostics = fl.DiagnosticsSummaryPanel(title="diagnostics",
                                             config=fl.DiagnosticsSummaryConfig(topic_to_render="/diagnostics"))
    safety = fl.DiagnosticsDetailPanel(title="safety", config=fl.DiagnosticsDetailConfig(
        topic_to_render="/safety/state", selected_hardware_id="racecar-hw", selected_name="safety"))
    logs = fl.LogPanel(title="log", config=fl.LogConfig(topic_to_render=LOG_TOPIC))
    v, w = teleop_speed_mps, teleop_yaw_rate
    teleop = fl.TeleopPanel(title="drive", config=fl.TeleopConfig(
        topic=FOXGLOVE_TELEOP_TOPIC, publish_rate=TELEOP_RATE_HZ,
        up_button=fl.TeleopButton(field="linear-x", value=v),
        down_button=fl.TeleopButton(field="linear-x", value=-v),
        left_button=fl.TeleopButton(field="angular-z", value=w),
        right_button=fl.TeleopButton(field="angular-z", value=-w)))
    estop = fl.ServiceCallPanel(title="e-stop", config=fl.ServiceCallConfig(
        service_name=SERVICE_PREFIX + "estop", request_payload="{}", button_text="E-STOP",
        button_color="#d61f1f", editing_mode=False))
    release = fl.ServiceCallPanel(title="release", config=fl.ServiceCallConfig(
        service_name=SERVICE_PREFIX + "release", request_payload="{}", button_text="release e-stop",
        button_color="#555555", editing_mode=False))

    def split(direction: str, *items: tuple[float, Any]) -> fl.SplitContainer:
        return fl.SplitContainer(direction=direction,  # type: ignore[arg-type]
                                 items=[fl.SplitItem(proportion=p, content=c) for p, c in items])

    controls = split("column", (1, estop), (1, release), (3, teleop))
    left = split("column", (3, three_d), (1, split("row", (2, logs), (1, controls))))
    right = split("column", (2, speeds), (1, steering), (1, source), (2, split("row", (1, diagnostics),
                                                                                 (1, safety))))
    return fl.Layout(content=split("row", (3, left), (2, right)))


def layout_json(layout: fl.Layout | None = None) -> str:
    """The layout as Foxglove imports it."""
    return json.dumps(json.loads((layout or build_layout()).to_json()), indent=2) + "\n"


def legacy_layout(layout: fl.Layout | None = None) -> dict[str, Any]:
    """The same panels in the older format (``configById`` and a binary split tree) Lichtblick imports."""
    tree = json.loads((layout or build_layout()).to_json())
    config_by_id: dict[str, Any] = {}

    def convert(node: dict[str, Any]) -> Any:
        if node.get("type") == "panel" or "panelType" in node:
            kind = LEGACY_PANEL_TYPES.get(node["panelType"], node["panelType"])
            ident = f"{kind}!{len(config_by_id) + 1:x}"
            config = dict(node.get("config", {}))
            if node.get("title"):  # Foxglove Studio 1.x reads the first key, Lichtblick the second
                config["foxglovePanelTitle"] = node["title"]
                config["lichtblickPanelTitle"] = node["title"]
            config_by_id[ident] = config
            return ident
        items = node["items"]
        direction = node["direction"]
        return split(direction, [(float(i["proportion"]), convert(i["content"])) for i in items])

    def split(direction: str, items: list[tuple[float, Any]]) -> Any:
        if len(items) == 1:
            return items[0][1]
        first_p, first = items[0]
        rest = split(direction, items[1:])
        total = first_p + sum(p for p, _ in items[1:])
        return {"direction": direction, "first": first, "second": rest,
                "splitPercentage": round(100.0 * first_p / total, 2)}

    mosaic = convert(tree["content"])
    return {"configById": config_by_id, "globalVariables": {}, "userNodes": {},
            "playbackConfig": {"speed": 1.0}, "layout": mosaic}


def write_layouts(directory: Path) -> list[Path]:
    """Write both layout files into ``directory``; returns their paths."""
    directory.mkdir(parents=True, exist_ok=True)
    foxglove_file, lichtblick_file = (directory / name for name in FILES)
    foxglove_file.write_text(layout_json())
    lichtblick_file.write_text(json.dumps(legacy_layout(), indent=2) + "\n")
    return [foxglove_file, lichtblick_file]


def main(argv: list[str] | None = None) -> int:
    """``python -m racecar_hw.net.layout [DIR]``: write the layouts (and print their paths)."""
    import argparse  # noqa: PLC0415 - only the command line needs it

    from racecar_hw.base.resources import config_dir  # noqa: PLC0415

    parser = argparse.ArgumentParser(prog="python -m racecar_hw.net.layout",
                                     description="Write the Foxglove and Lichtblick layouts.")
    parser.add_argument("directory", nargs="?", type=Path, default=None,
                        help="where to write them (default: the shipped config/foxglove)")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    directory = args.directory if args.directory is not None else config_dir() / "foxglove"
    for path in write_layouts(directory):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())

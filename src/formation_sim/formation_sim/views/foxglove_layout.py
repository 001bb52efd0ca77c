"""The Foxglove layout of a formation: a 3D view of ``/formation/markers`` beside plots of every edge's
e and ψ in their funnels (``/formation/funnels``), with a link model the age of each link's held
sample (``/formation/links``), and the agents' ``/diagnostics``.

Made from the formation (no ROS), so that every run can leave the layout of its own formation in
OUT (``foxglove_layout.json``); ``foxglove/formation_layout.json`` is the paper scenario's. A plot
names each line by edge and quantity and shows no values in its legend (a legend of values is
unreadable while a run plays, and it cut the names); edges whose funnels are the same (the same C_col, C_con and
performance function) share one pair of bound lines, labelled with every edge they bound.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from formation_core.formation import EdgeSpec, FormationSpec
from formation_msgs_py import topics
from formation_sim.views.display_wire import FUNNEL_FIELDS

LAYOUT_NAME = "foxglove_layout.json"
#: colours of the edges' error lines (matplotlib's tab10): a bound line is grey
EDGE_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22")
BOUND_COLOURS = ("#555555", "#999999", "#000000", "#777777")


def _path(k: int, field: str, label: str, colour: str, width: float) -> dict[str, Any]:
    """One plotted line: field ``field`` of edge ``k`` in ``/formation/funnels``."""
    index = k * len(FUNNEL_FIELDS) + FUNNEL_FIELDS.index(field)
    return {
        "value": f"/{topics.FUNNELS}.data[{index}]",
        "enabled": True,
        "timestampMethod": "receiveTime",
        "label": label,
        "color": colour,
        "lineSize": width,
    }


def _groups(edges: list[EdgeSpec], key: Callable[[EdgeSpec], tuple]) -> list[list[int]]:
    """Indices of the edges, grouped by equal ``key`` (their funnels), in file order."""
    groups: dict[tuple, list[int]] = {}
    for k, e in enumerate(edges):
        groups.setdefault(key(e), []).append(k)
    return list(groups.values())


def _distance_funnel(e: EdgeSpec) -> tuple:
    return (e.c_col, e.c_con, e.rho_e_inf, e.decay_e)


def _orientation_funnel(e: EdgeSpec) -> tuple:
    return (e.rho_psi_0, e.rho_psi_inf, e.decay_psi)


def _plot(title: str, lines: list[dict[str, Any]]) -> dict[str, Any]:
    return {
        "title": title,
        "paths": lines,
        "showXAxisLabels": True,
        "showYAxisLabels": True,
        "showLegend": True,
        # beside the plot, wide enough for the longest name: on top it takes most of a short panel's height
        "legendDisplay": "left",
        "sidebarDimension": 320,
        "showPlotValuesInLegend": False,
        "isSynced": True,
        "xAxisVal": "timestamp",
    }


def _bounds(edges: list[EdgeSpec], groups: list[list[int]], fields: tuple[tuple[str, str], ...]) -> list[dict]:
    out: list[dict[str, Any]] = []
    for g, members in enumerate(groups):
        names = ", ".join(edges[k].name for k in members)
        colour = BOUND_COLOURS[g % len(BOUND_COLOURS)]
        out.extend(_path(members[0], field, f"{label} ({names})", colour, 0.8) for field, label in fields)
    return out


def foxglove_layout(spec: FormationSpec) -> dict[str, Any]:
    """The layout (Foxglove's JSON, as its Import button reads it) for ``spec``."""
    edges = list(spec.edges)
    colour = [EDGE_COLOURS[k % len(EDGE_COLOURS)] for k in range(len(edges))]
    distance = [_path(k, "e", f"e {e.name}", colour[k], 1.5) for k, e in enumerate(edges)]
    distance += _bounds(edges, _groups(edges, _distance_funnel), (("e_upper", "C_con·ρ_e"), ("e_lower", "−C_col·ρ_e")))
    orientation = [_path(k, "psi", f"ψ {e.name}", colour[k], 1.5) for k, e in enumerate(edges)]
    orientation += _bounds(edges, _groups(edges, _orientation_funnel), (("rho_psi", "ρ_ψ"),))
    return {
        "configById": {
            "3D!formation": {
                "followTf": "world",
                "followMode": "follow-none",
                "scene": {"enableStats": False},
                "transforms": {},
                "topics": {f"/{topics.MARKERS}": {"visible": True}, f"/{topics.GROUND_TRUTH}": {"visible": False}},
                "layers": {
                    "grid": {
                        "visible": True,
                        "frameLocked": True,
                        "label": "Grid",
                        "instanceId": "grid",
                        "layerId": "foxglove.Grid",
                        "size": 10,
                        "divisions": 10,
                        "lineWidth": 1,
                        "color": "#248eff",
                        "position": [0, 0, 0],
                        "rotation": [0, 0, 0],
                        "order": 1,
                    }
                },
                "cameraState": {
                    "distance": 14,
                    "perspective": True,
                    "phi": 60,
                    "thetaOffset": 45,
                    "target": [0, 0, 1],
                    "targetOffset": [0, 0, 0],
                    "targetOrientation": [0, 0, 0, 1],
                    "fovy": 45,
                    "near": 0.01,
                    "far": 5000,
                },
            },
            "Plot!distance": _plot(f"distance errors e_k [m²] in their funnels (/{topics.FUNNELS})", distance),
            "Plot!orientation": _plot(f"orientation errors ψ_k [-] under ρ_ψ (/{topics.FUNNELS})", orientation),
            "DiagnosticSummary!agents": {"topicToRender": topics.DIAGNOSTICS},
            **({"Plot!links": _link_ages_plot(spec)} if spec.has_links else {}),
        },
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1},
        "layout": {
            "direction": "row",
            "first": "3D!formation",
            "second": _right_column(spec.has_links),
            "splitPercentage": 55,
        },
    }


def _right_column(links: bool) -> dict[str, Any]:
    """The plots above the diagnostics; with a link model the link ages get a row of their own, as wide
    as the funnels' (beside the diagnostics its legend leaves the lines no room)."""
    if not links:
        below: dict[str, Any] = {
            "direction": "column",
            "first": "Plot!orientation",
            "second": "DiagnosticSummary!agents",
        }
        return {
            "direction": "column",
            "first": "Plot!distance",
            "second": {**below, "splitPercentage": 65},
            "splitPercentage": 45,
        }
    tail: dict[str, Any] = {
        "direction": "column",
        "first": "Plot!links",
        "second": "DiagnosticSummary!agents",
        "splitPercentage": 70,
    }
    below = {"direction": "column", "first": "Plot!orientation", "second": tail, "splitPercentage": 40}
    return {"direction": "column", "first": "Plot!distance", "second": below, "splitPercentage": 33}


def _link_ages_plot(spec: FormationSpec) -> dict[str, Any]:
    """Every link's held sample's age [s] (``/formation/links``, one value per link)."""
    from formation_core.formation import simulator_view
    from formation_sim.core.links import CHANNELS, link_names

    names = link_names(simulator_view(spec))
    labels = [f"{channel} {name}" for channel in CHANNELS for name in names[channel]]
    lines = [
        {
            "value": f"/{topics.LINKS}.data[{j}]",
            "enabled": True,
            "timestampMethod": "receiveTime",
            "label": label,
            "color": EDGE_COLOURS[j % len(EDGE_COLOURS)],
            "lineSize": 1.0,
        }
        for j, label in enumerate(labels)
    ]
    return _plot(f"age of each link's held sample [s] (/{topics.LINKS})", lines)


def layout_text(spec: FormationSpec) -> str:
    """:func:`foxglove_layout` as the text of a file (indented JSON, UTF-8, a final newline)."""
    return json.dumps(foxglove_layout(spec), indent=2, ensure_ascii=False) + "\n"


def write_layout(out_dir: Path, spec: FormationSpec) -> Path:
    """Write ``out_dir/foxglove_layout.json`` atomically; returns its path."""
    from formation_core.faults import write_atomic

    path = out_dir / LAYOUT_NAME
    write_atomic(path, layout_text(spec).encode())
    return path

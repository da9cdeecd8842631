"""The one Rerun blueprint sent with every recording: the scene and the paper's figures.

Left: the 3D scene (drawn from the MuJoCo model, with ghost poses, the desired path, the
tool trace, force arrows and the HMD frustum), the operator's eye view and the event log.
Right, in tabs: the scenario's figures (path following: paper Figs. 8 and 9;
teleoperation: Figs. 12 and 13 and the feedback forces), then loop rates and per-hop
latency.

The layout is data (:func:`view_specs`), so the tests can check that a recording holds
every entity the blueprint shows.
"""

from __future__ import annotations

from dataclasses import dataclass

import rerun.blueprint as rrb

from teleop.core.config import Config
from teleop.viz import entities as r

# Where the 3D view's eye starts (world frame, m): behind and above the table, looking at
# the arm's workspace.
EYE_POSITION_M = (-1.1, -1.3, 0.9)
EYE_LOOK_TARGET_M = (0.3, 0.0, 0.15)
EYE_UP = (0.0, 0.0, 1.0)
# Share of the window width of the left (scene) and right (figures) columns.
COLUMN_SHARES = (3.0, 2.0)
# Share of the left column's height of the 3D view and the row below it.
SCENE_ROW_SHARES = (3.0, 1.0)


@dataclass(frozen=True)
class ViewSpec:
    """One view of the blueprint: its kind, title, and the entities it shows.

    ``entities`` are exact entity paths; ``subtrees`` are roots whose whole subtree is
    shown (their children are only known once the data arrives: loop rates, hops).
    """

    kind: str  # "3d", "2d", "series" or "log"
    name: str
    entities: tuple[str, ...] = ()
    subtrees: tuple[str, ...] = ()


def _xyz(base: str) -> tuple[str, ...]:
    return tuple(r.axis_entity(base, axis) for axis in r.AXES)


def _per_axis(name: str, first: str, second: str) -> tuple[ViewSpec, ...]:
    """One series view per axis, each with the same coordinate of two vectors."""
    return tuple(
        ViewSpec(
            "series", f"{name}, {axis}", (r.axis_entity(first, axis), r.axis_entity(second, axis))
        )
        for axis in r.AXES
    )


def scene_views() -> tuple[ViewSpec, ...]:
    """The left column: 3D scene, operator's eye view, event log."""
    return (
        ViewSpec("3d", "Scene", subtrees=(r.ENTITY_WORLD,)),
        ViewSpec("2d", "Operator's eye view", subtrees=(r.ENTITY_EYE_VIEW,)),
        ViewSpec("log", "Events", subtrees=(r.ENTITY_EVENTS,)),
    )


def figure_tabs(config: Config) -> tuple[tuple[str, tuple[ViewSpec, ...]], ...]:
    """The right column's tabs, (title, views), for the config's scenario."""
    timing = (
        "Timing",
        (
            ViewSpec("series", "Loop rates (Hz)", subtrees=(r.ENTITY_RATES,)),
            ViewSpec("series", "Latency per hop (ms)", subtrees=(r.ENTITY_LATENCY,)),
        ),
    )
    if config.run.scenario == "path-following":
        path = (
            "Path following",
            (
                ViewSpec("series", "Path error (m), Fig. 9", (r.ENTITY_PATH_ERROR,)),
                *_per_axis(
                    "Desired vs actual tool path (m), Fig. 8", r.ENTITY_DESIRED_P, r.ENTITY_TOOL_P
                ),
            ),
        )
        return (path, timing)
    teleop = (
        "Teleoperation",
        (
            *_per_axis(
                "Operator reference vs tool velocity (m/s), Fig. 12",
                r.ENTITY_TELEOP_V_REF,
                r.ENTITY_TELEOP_V_TOOL,
            ),
            ViewSpec("series", "Control error (m/s), Fig. 13", _xyz(r.ENTITY_TELEOP_V_ERROR)),
        ),
    )
    forces = (
        "Force feedback",
        (
            ViewSpec(
                "series",
                "Feedback force norms (N)",
                tuple(r.norm_entity(c) for c in r.FEEDBACK_COMPONENTS),
            ),
            ViewSpec(
                "series", "Force on the device (N, device frame)", _xyz(r.ENTITY_FEEDBACK_DEVICE_F)
            ),
            ViewSpec(
                "series",
                "Passivity at the handle (J): observed energy, dissipated",
                (r.ENTITY_PASSIVITY_OBSERVED, r.ENTITY_PASSIVITY_DISSIPATED),
            ),
        ),
    )
    return (teleop, forces, timing)


def view_specs(config: Config) -> tuple[ViewSpec, ...]:
    """Every view of the blueprint for this config, left column first."""
    tabs = tuple(spec for _, views in figure_tabs(config) for spec in views)
    return scene_views() + tabs


def _view(spec: ViewSpec) -> rrb.View:
    contents = [*spec.entities, *(f"{root}/**" for root in spec.subtrees)]
    if spec.kind == "3d":
        return rrb.Spatial3DView(
            origin=spec.subtrees[0],
            name=spec.name,
            eye_controls=rrb.EyeControls3D(
                position=EYE_POSITION_M, look_target=EYE_LOOK_TARGET_M, eye_up=EYE_UP
            ),
        )
    if spec.kind == "2d":
        return rrb.Spatial2DView(origin=spec.subtrees[0], name=spec.name)
    if spec.kind == "log":
        return rrb.TextLogView(origin=spec.subtrees[0], name=spec.name)
    return rrb.TimeSeriesView(origin="/", contents=contents, name=spec.name)


def build_blueprint(config: Config) -> rrb.Blueprint:
    """The blueprint of a run of ``config``: scene column and figure tabs, sim time."""
    scene, eye, log = (_view(spec) for spec in scene_views())
    left = rrb.Vertical(scene, rrb.Horizontal(eye, log), row_shares=list(SCENE_ROW_SHARES))
    tabs = [
        rrb.Vertical(*(_view(spec) for spec in views), name=title)
        for title, views in figure_tabs(config)
    ]
    return rrb.Blueprint(
        rrb.Horizontal(left, rrb.Tabs(*tabs), column_shares=list(COLUMN_SHARES)),
        rrb.TimePanel(timeline=r.TIMELINE_SIM),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )

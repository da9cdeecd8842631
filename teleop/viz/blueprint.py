"""The one Rerun blueprint sent with every recording: the scene and the paper's figures.

Left: the 3D scene (drawn from the MuJoCo model, with ghost poses, the desired path, the
tool trace, force arrows and the HMD frustum), the operator's eye view and the event log.
Right, in tabs: the scenario's figures (path following: paper Figs. 8 and 9;
teleoperation: Figs. 12 and 13 and the feedback forces), then loop rates and per-hop
latency.

A run of several robots (teleop.viz.entities ``entity_roots``): one 3D view with every
robot side by side (:func:`robot_offset_m`), each robot's eye view in a tab, one event
log of all, and each robot's figure tabs, titled with its id.

The layout is data (:func:`view_specs`), so the tests can check that a recording holds
every entity the blueprint shows.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import rerun.blueprint as rrb

from teleop.core.config import Config
from teleop.viz import entities as r

# Where the 3D view's eye starts (world frame, m): behind and above the table, looking at
# the arm's workspace.
EYE_POSITION_M = (-1.1, -1.3, 0.9)
EYE_LOOK_TARGET_M = (0.3, 0.0, 0.15)
EYE_UP = (0.0, 0.0, 1.0)
# Robots of one run stand this far apart along the world's y axis in the 3D view (m): the
# scene's table is 1.4 m wide, so an aisle of 0.2 m between two tables.
ROBOT_SPACING_M = 1.6
# Share of the window width of the left (scene) and right (figures) columns.
COLUMN_SHARES = (3.0, 2.0)
# Share of the left column's height of the 3D view and the row below it.
SCENE_ROW_SHARES = (3.0, 1.0)


@dataclass(frozen=True)
class ViewSpec:
    """One view of the blueprint: its kind, title, and the entities it shows.

    ``entities`` are exact entity paths; ``subtrees`` are roots whose whole subtree is
    shown (their children are only known once the data arrives: loop rates, hops). A
    view of one subtree has it as its origin; of several, the recording's root.
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


def robot_offset_m(index: int) -> tuple[float, float, float]:
    """Where the world of the run's robot ``index`` stands in a recording of several
    (m, in the recording's root frame): side by side along y."""
    return (0.0, index * ROBOT_SPACING_M, 0.0)


def _roots(config: Config) -> tuple[str, ...]:
    return r.entity_roots(config.robot_ids())


def _under(root: str, spec: ViewSpec) -> ViewSpec:
    """``spec`` for the robot of entity root ``root`` (the empty root: as it is)."""
    if not root:
        return spec
    return replace(
        spec,
        name=f"{root}: {spec.name}",
        entities=tuple(r.rooted(root, e) for e in spec.entities),
        subtrees=tuple(r.rooted(root, e) for e in spec.subtrees),
    )


def scene_views(config: Config) -> tuple[ViewSpec, ...]:
    """The left column: the 3D scene of every robot, each robot's eye view, the event
    log of all."""
    roots = _roots(config)
    named = f"Scene: {', '.join(roots)}" if len(roots) > 1 else "Scene"
    return (
        ViewSpec("3d", named, subtrees=tuple(r.rooted(root, r.ENTITY_WORLD) for root in roots)),
        *(
            _under(root, ViewSpec("2d", "Operator's eye view", subtrees=(r.ENTITY_EYE_VIEW,)))
            for root in roots
        ),
        ViewSpec(
            "log", "Events", subtrees=tuple(r.rooted(root, r.ENTITY_EVENTS) for root in roots)
        ),
    )


def figure_tabs(config: Config) -> tuple[tuple[str, tuple[ViewSpec, ...]], ...]:
    """The right column's tabs, (title, views), for the config's scenario: each robot's,
    titled with its id when there are several."""
    return tuple(
        (f"{root}: {title}" if root else title, tuple(_under(root, spec) for spec in views))
        for root in _roots(config)
        for title, views in _robot_tabs(config)
    )


def _robot_tabs(config: Config) -> tuple[tuple[str, tuple[ViewSpec, ...]], ...]:
    """One robot's figure tabs, (title, views), entities under the empty root."""
    timing = (
        "Timing",
        (
            ViewSpec("series", "Loop rates (Hz)", subtrees=(r.ENTITY_RATES,)),
            ViewSpec("series", "Latency per hop (ms)", subtrees=(r.ENTITY_LATENCY,)),
        ),
    )
    if config.run.follows_path:
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
    return scene_views(config) + tabs


def _eye_controls(robots: int) -> rrb.EyeControls3D:
    """The 3D view's starting eye: on one robot's workspace, or back far enough to see
    every robot, looking at the middle of the row."""
    middle_m = robot_offset_m(robots - 1)[1] / 2.0
    scale = 1.0 + 0.5 * (robots - 1)
    target = (EYE_LOOK_TARGET_M[0], EYE_LOOK_TARGET_M[1] + middle_m, EYE_LOOK_TARGET_M[2])
    position = tuple(
        t + scale * (p - t0)
        for t, p, t0 in zip(target, EYE_POSITION_M, EYE_LOOK_TARGET_M, strict=True)
    )
    return rrb.EyeControls3D(position=position, look_target=target, eye_up=EYE_UP)


def _view(spec: ViewSpec, robots: int = 1) -> rrb.View:
    origin = spec.subtrees[0] if len(spec.subtrees) == 1 else "/"
    contents = [*spec.entities, *(f"{root}/**" for root in spec.subtrees)]
    if spec.kind == "3d":
        return rrb.Spatial3DView(
            origin=origin, contents=contents, name=spec.name, eye_controls=_eye_controls(robots)
        )
    if spec.kind == "2d":
        return rrb.Spatial2DView(origin=origin, name=spec.name)
    if spec.kind == "log":
        return rrb.TextLogView(origin=origin, contents=contents, name=spec.name)
    return rrb.TimeSeriesView(origin="/", contents=contents, name=spec.name)


def build_blueprint(config: Config) -> rrb.Blueprint:
    """The blueprint of a run of ``config``: scene column and figure tabs, sim time."""
    scene, *eyes, log = scene_views(config)
    robots = len(eyes)
    eye = _view(eyes[0]) if robots == 1 else rrb.Tabs(*(_view(spec) for spec in eyes))
    left = rrb.Vertical(
        _view(scene, robots), rrb.Horizontal(eye, _view(log)), row_shares=list(SCENE_ROW_SHARES)
    )
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

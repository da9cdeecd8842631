"""A run split across hosts: the robot site makes the run's identities once and hands
every other site its own in one file (docs/sites.md).

``teleop up --site robot --site-listen tls/ADDR:PORT`` makes every participant's
identity (every site's services, every site's router, one observer per site), starts
its own services and router, and writes a bundle per other site in its run directory:
:data:`OPERATOR_BUNDLE_FILE` for the operator site and, in a run of several robots
(``run.robots``), :func:`robot_bundle_file` for each other robot's site. A bundle holds
that site's identities (certificates and private keys inline, the run's authority
certificate, the access-control list), where its router connects, and the run's settings
(mode, scenario, overrides), so every site runs the same run. The user copies each file
to its host, privately (it holds private keys; scp keeps it 0600), and ``teleop up
--site operator --join FILE`` (or ``--site robot --join FILE``) writes the identities
into its own run directory and starts that site. Nothing of it is ever committed or sent
over the bus.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from teleop.bus import graph
from teleop.bus.access import (
    export_identities,
    import_identities,
    site_observer,
    write_private,
)
from teleop.core.config import OPERATOR_SITE, ROBOT_SITE, SITES, Config
from teleop.core.rundir import AUTH_DIR

OPERATOR_BUNDLE_FILE = "operator-site.json"
BUNDLE_FORMAT = "teleop-site/2"
# Overrides a site chooses for itself, not handed over: its role, its local endpoint.
_LOCAL_OVERRIDES = ("site.", "bus.endpoint")


class SiteError(ValueError):
    """A site's settings or bundle cannot make a run; the message says what to do."""


def robot_bundle_file(robot_id: str) -> str:
    """The bundle of the site of robot ``robot_id`` (not the first) of a run of several."""
    return f"robot-site-{robot_id}.json"


def check_site(config: Config) -> None:
    """SiteError unless ``config`` can run one site of a run across hosts."""
    site = config.site
    if not site.name:
        return
    if not config.run.teleoperated:
        raise SiteError(
            f"{config.run.scenario} has no operator site (nobody at the handle): sites "
            "split a teleoperated run, e.g. --set 'run.scenario=\"grasp\"'"
        )
    if not config.bus.mutual_tls:
        raise SiteError("sites link over mutual TLS only: drop bus.secure=false / bus.tls=false")
    if site.robot and site.robot not in config.robot_ids()[1:]:
        raise SiteError(
            f"site.robot={site.robot}: not a robot of this run other than the first "
            f"({', '.join(config.robot_ids())}); join with the bundle the first robot's "
            "site wrote for it"
        )
    if site.name == ROBOT_SITE and not site.robot and not site.listen:
        raise SiteError(
            "the robot site listens for the other sites: --site-listen tls/ADDRESS:PORT "
            "(an address of this host the others reach)"
        )
    if (site.name == OPERATOR_SITE or site.robot) and not site.connect:
        raise SiteError(
            f"the {site.name} site connects to the first robot's site: --connect tls/ADDRESS:PORT"
        )


def site_links(robot_ids: Sequence[str]) -> list[str]:
    """The routers and the observers of every site of a run of ``robot_ids`` across
    hosts: the operator site's, the first robot's, and each other robot's site's."""
    sites = [(OPERATOR_SITE, ""), (ROBOT_SITE, "")]
    sites += [(ROBOT_SITE, robot_id) for robot_id in robot_ids[1:]]
    return [
        name
        for site, robot_id in sites
        for name in (graph.router_instance(site, robot_id), site_observer(site, robot_id))
    ]


def site_participants(
    site: str, robot_id: str, scenario: Sequence[str], robot_ids: Sequence[str]
) -> list[str]:
    """The participants ``site`` runs in a run of ``robot_ids`` (``scenario``: its
    processes, graph.instances): its services of ``scenario``, its router and its
    observer. ``robot_id``: another robot's site (its robot's instances only); empty:
    the operator site, or the first robot's (the services of the whole run too)."""
    here = [
        name for name in graph.on_site(scenario, site) if _runs(name, site, robot_id, robot_ids)
    ]
    return [*here, graph.router_instance(site, robot_id), site_observer(site, robot_id)]


def _runs(name: str, site: str, robot_id: str, robot_ids: Sequence[str]) -> bool:
    """Whether the site of ``robot_id`` ("": the first's, or the operator's) runs
    ``name``, an instance of its own site's services."""
    if site != ROBOT_SITE or len(robot_ids) == 1:
        return True
    robot = graph.robot_of(name)
    return robot == (robot_id or robot_ids[0]) or (robot is None and not robot_id)


def write_site_bundles(
    run_dir: Path,
    config: Config,
    overrides: Sequence[str],
    credentials: Mapping[str, Path],
    scenario: Sequence[str],
) -> list[tuple[str, Path]]:
    """The first robot's site writes the other sites' bundles (mode 0600) in ``run_dir``,
    each site's name and its file:
    the operator site's, and in a run of several robots each other robot's site's; each
    with the identities of its :func:`site_participants`, the hub's ``site.listen`` to
    connect to, and the run's ``overrides`` (those a site chooses for itself left out)."""
    robot_ids = config.robot_ids()
    sites = [(OPERATOR_SITE, "", OPERATOR_BUNDLE_FILE)]
    sites += [(ROBOT_SITE, rid, robot_bundle_file(rid)) for rid in robot_ids[1:]]
    paths = []
    for site, robot_id, file in sites:
        names = site_participants(site, robot_id, scenario, robot_ids)
        bundle = {
            "format": BUNDLE_FORMAT,
            "site": site,
            "site_robot": robot_id,
            "robot_id": config.robot.robot_id,
            "connect": config.site.listen,
            "overrides": [o for o in overrides if not o.strip().startswith(_LOCAL_OVERRIDES)],
            "identities": export_identities({name: credentials[name] for name in names}),
        }
        path = Path(run_dir).absolute() / file
        write_private(path, json.dumps(bundle, indent=1))
        paths.append((site, path))
    return paths


@dataclass(frozen=True)
class JoinedSite:
    """What a bundle gives the site that joins with it: the run's overrides (its own
    site's among them), where to connect, and its participants' credentials files
    (written into its run directory)."""

    overrides: list[str]
    connect: str
    credentials: dict[str, Path]


def join_site(site: str, bundle_path: Path, run_dir: Path) -> JoinedSite:
    """Read a bundle for ``site`` and write its identities into ``run_dir``'s ``auth``
    directory; SiteError (one line: what is wrong, what to do) if it is unreadable, not
    a bundle, another site's, or readable by other users."""
    path = Path(bundle_path)
    try:
        mode = path.stat().st_mode
        content: Any = json.loads(path.read_text())
    except OSError as exc:
        raise SiteError(f"{path}: {exc.strerror}; copy the robot site's bundle") from None
    except ValueError as exc:
        raise SiteError(f"{path}: not JSON ({exc}); copy the robot site's file again") from None
    if mode & 0o077:
        raise SiteError(
            f"{path} holds private keys and others may read it (mode {mode & 0o777:o}): "
            f"chmod 600 {path}"
        )
    if not isinstance(content, dict) or content.get("format") != BUNDLE_FORMAT:
        raise SiteError(f"{path}: not a site bundle of this version ({BUNDLE_FORMAT})")
    if content.get("site") not in SITES or content["site"] != site:
        raise SiteError(
            f"{path}: the bundle of the {content.get('site')} site, not of the {site} site "
            f"(the robot site wrote {OPERATOR_BUNDLE_FILE} for the operator's host, "
            f"{robot_bundle_file('<robot>')} for each other robot's)"
        )
    try:
        credentials = import_identities(Path(run_dir).absolute() / AUTH_DIR, content["identities"])
        overrides = [str(o) for o in content["overrides"]]
        overrides.append(f"robot.robot_id={json.dumps(str(content['robot_id']))}")
        if content["site_robot"]:
            overrides.append(f"site.robot={json.dumps(str(content['site_robot']))}")
        return JoinedSite(overrides, str(content["connect"]), credentials)
    except (KeyError, TypeError, ValueError) as exc:
        raise SiteError(
            f"{path}: malformed bundle ({exc!r}); copy the robot site's file again"
        ) from None

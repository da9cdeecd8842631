"""A run split across two hosts: the robot site makes the run's identities once and
hands the operator site its own in one file (docs/sites.md).

``teleop up --site robot --site-listen tls/ADDR:PORT`` makes every participant's
identity (both sites' services, both routers, one observer per site), starts its own
services and router, and writes :data:`OPERATOR_BUNDLE_FILE` in its run directory: the
operator site's identities (certificates and private keys inline, the run's authority
certificate, the access-control list), where its router connects, and the run's
settings (mode, scenario, overrides), so both sites run the same run. The user copies
that file to the other host, privately (it holds private keys; scp keeps it 0600), and
``teleop up --site operator --join FILE`` writes the identities into its own run
directory and starts the operator site. Nothing of it is ever committed or sent over
the bus.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from teleop.bus import graph
from teleop.bus.access import (
    OPERATOR_OBSERVER,
    export_identities,
    import_identities,
    write_private,
)
from teleop.core.config import OPERATOR_SITE, ROBOT_SITE, Config
from teleop.core.rundir import AUTH_DIR

OPERATOR_BUNDLE_FILE = "operator-site.json"
BUNDLE_FORMAT = "teleop-site/1"
# Overrides a site chooses for itself, not handed over: its role, its local endpoint.
_LOCAL_OVERRIDES = ("site.", "bus.endpoint")


class SiteError(ValueError):
    """A site's settings or bundle cannot make a run; the message says what to do."""


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
    if site.name == ROBOT_SITE and not site.listen:
        raise SiteError(
            "the robot site listens for the operator site: --site-listen tls/ADDRESS:PORT "
            "(an address of this host the other host reaches)"
        )
    if site.name == OPERATOR_SITE and not site.connect:
        raise SiteError("the operator site connects to the robot site: --connect tls/ADDRESS:PORT")


def operator_participants(scenario: Sequence[str]) -> list[str]:
    """The participants the operator site runs: its services of ``scenario``, its router
    and its observer."""
    return [*graph.on_site(scenario, OPERATOR_SITE), graph.router_name(OPERATOR_SITE),
            OPERATOR_OBSERVER]  # fmt: skip


def write_operator_bundle(
    run_dir: Path,
    config: Config,
    overrides: Sequence[str],
    credentials: Mapping[str, Path],
    scenario: Sequence[str],
) -> Path:
    """The operator site's bundle (:data:`OPERATOR_BUNDLE_FILE`, mode 0600) in
    ``run_dir``: the identities of :func:`operator_participants`, the robot site's
    ``site.listen`` to connect to, and the run's ``overrides`` (those a site chooses for
    itself left out)."""
    names = operator_participants(scenario)
    bundle = {
        "format": BUNDLE_FORMAT,
        "robot_id": config.robot.robot_id,
        "connect": config.site.listen,
        "overrides": [o for o in overrides if not o.strip().startswith(_LOCAL_OVERRIDES)],
        "identities": export_identities({name: credentials[name] for name in names}),
    }
    path = Path(run_dir).absolute() / OPERATOR_BUNDLE_FILE
    write_private(path, json.dumps(bundle, indent=1))
    return path


@dataclass(frozen=True)
class OperatorSite:
    """What a bundle gives the operator site: the run's overrides, where to connect,
    and its participants' credentials files (written into its run directory)."""

    overrides: list[str]
    connect: str
    credentials: dict[str, Path]


def join_operator_site(bundle_path: Path, run_dir: Path) -> OperatorSite:
    """Read the robot site's bundle and write its identities into ``run_dir``'s
    ``auth`` directory; SiteError (one line: what is wrong, what to do) if it is
    unreadable, not a bundle, or readable by other users."""
    path = Path(bundle_path)
    try:
        mode = path.stat().st_mode
        content: Any = json.loads(path.read_text())
    except OSError as exc:
        raise SiteError(
            f"{path}: {exc.strerror}; copy the robot site's {OPERATOR_BUNDLE_FILE}"
        ) from None
    except ValueError as exc:
        raise SiteError(f"{path}: not JSON ({exc}); copy the robot site's file again") from None
    if mode & 0o077:
        raise SiteError(
            f"{path} holds private keys and others may read it (mode {mode & 0o777:o}): "
            f"chmod 600 {path}"
        )
    if not isinstance(content, dict) or content.get("format") != BUNDLE_FORMAT:
        raise SiteError(f"{path}: not a site bundle of this version ({BUNDLE_FORMAT})")
    try:
        credentials = import_identities(Path(run_dir).absolute() / AUTH_DIR, content["identities"])
        overrides = [str(o) for o in content["overrides"]]
        overrides.append(f"robot.robot_id={json.dumps(str(content['robot_id']))}")
        return OperatorSite(overrides, str(content["connect"]), credentials)
    except (KeyError, TypeError, ValueError) as exc:
        raise SiteError(
            f"{path}: malformed bundle ({exc!r}); copy the robot site's file again"
        ) from None

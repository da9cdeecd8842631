"""Who may say what on a stack's bus: per-run identities and an access-control list,
both derived from the one description of the graph (:mod:`teleop.bus.graph`).

A launcher (``teleop run``, ``teleop up``, ``teleop latency``) gives every process of the
run (every service, the launcher itself, an outside client, the read-only observer) a
name and a random Zenoh id, and writes each one a file only its user can read
(:func:`write_run_credentials`). :func:`teleop.bus.session.open_session` loads a
process's file (``bus.credentials_file``) into its Zenoh config.

With ``bus.tls`` (the default) the identity is a certificate: the launcher makes a
certificate authority for the run (its key never written) and one certificate and key
per participant (:mod:`teleop.bus.tls`). Every link is mutual TLS, so both of its ends
are authenticated, and a participant's file names its own key and the authority's
(public) certificate only: no file reveals another participant's secret. The
access-control list (default deny, the same in every process) knows a peer as a
participant only if both its certificate's common name and its session's Zenoh id are
that participant's: a second session holding a participant's certificate but its own
id gets no right at all, and Zenoh refuses a second session with an id already linked.
So one session per participant: the controller's commands come from the controller's
session or not at all.

Without TLS (``bus.tls = false``), Zenoh's user/password authentication closes the bus:
a link is accepted only from a process presenting a user and password of the run's
dictionary, which every process that accepts links must hold (so a service's file does
reveal the others' passwords; the observer's, which accepts no links, does not). The
list then knows a peer by its Zenoh id only: user/password authenticates the process
that opens a link to the one that accepts it, not the other way round, and a name
matched on its own would let any holder of a participant's password in with any id.

Either way a participant may publish only the streams the graph lists it as producing,
subscribe only to those it consumes, and declare only its own liveliness tokens. See
docs/protocol.md, "Access control".
"""

from __future__ import annotations

import json
import os
import secrets
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from teleop.bus import graph
from teleop.bus.graph import ALIVE_TOKEN, PROTOCOL_TOKEN, READY_TOKEN, RELEASED_TOKEN, ROOT
from teleop.bus.messages import PROTOCOL_VERSION
from teleop.core.config import OPERATOR_SITE

# The certificates are made here, by a launcher; a service only reads its credentials
# file. teleop.bus.tls brings the cryptography package (about 40 ms to import): it is
# imported where a certificate is made, so that no service pays for it at each (re)start.
if TYPE_CHECKING:
    from teleop.bus.tls import Issued

# The launcher's own session (teleop run): it consumes the streams the graph lists for
# "launcher" and declares its tokens under this name.
LAUNCHER = "launcher"
# A read-only participant every launcher adds: it may subscribe to every stream and
# publish nothing (a user's own plotting script, a test watching the bus). A run split
# across hosts has one per site (each site's launcher watches its own services).
OBSERVER = "observer"
OPERATOR_OBSERVER = "operator_observer"
OBSERVERS = (OBSERVER, OPERATOR_OBSERVER)
# Without TLS: the run's dictionary of user:password lines (what every process that
# accepts links checks a new link against).
PASSWORDS_FILE = "passwords"
# With TLS: the run's certificate authority (every process's root of trust), and each
# participant's certificate and private key (<name> + suffix).
CA_FILE = "ca.pem"
CERTIFICATE_SUFFIX = ".cert.pem"
PRIVATE_KEY_SUFFIX = ".key.pem"
# Zenoh's TLS settings (config path prefix).
TLS_CONFIG = "transport/link/tls"
# Message kinds of Zenoh's access control, by what they carry.
_LIVELINESS_WATCH = ["declare_liveliness_subscriber", "liveliness_query"]
_NAME_ALPHABET = frozenset("abcdefghijklmnopqrstuvwxyz0123456789_-")


@dataclass(frozen=True)
class Credentials:
    """One participant's identity on the run's bus."""

    user: str  # the participant's name
    password: str  # user/password authentication (runs without TLS only)
    zid: str  # Zenoh id, 32 hex digits, the first not 0 (Zenoh refuses leading zeros)

    @classmethod
    def generate(cls, name: str) -> Credentials:
        if not name or not set(name) <= _NAME_ALPHABET:
            raise ValueError(f"participant name {name!r}: lower-case letters, digits, _ and -")
        return cls(name, secrets.token_hex(16), new_zid())


def new_zid() -> str:
    """A random Zenoh id: 32 hex digits, the first not 0 (Zenoh refuses leading zeros)."""
    return format(secrets.randbits(127) | 1 << 127, "032x")


def site_observer(site: str, robot_id: str = "") -> str:
    """The observer participant of ``site`` (empty: a one-host run's); of the robot site
    of a robot other than the first (``robot_id``, graph.router_instance), its own
    instance, watching that robot's keys alone."""
    if site == OPERATOR_SITE:
        return OPERATOR_OBSERVER
    return f"{OBSERVER}{graph.INSTANCE_SEPARATOR}{robot_id}" if robot_id else OBSERVER


def rights(participant: str) -> tuple[list[str], list[str]]:
    """Keys (after ``teleop/<robot>/``) the graph lets ``participant`` publish and
    subscribe to (an observer: none, and every stream; a site's router, which forwards
    the other site's streams: every stream both ways)."""
    every = [s.key for s in graph.STREAMS]
    if graph.role_of(participant) in OBSERVERS:
        return [], every
    if graph.is_router(participant):
        return every, every
    produces = [s.key for s in graph.STREAMS if participant in s.producers]
    consumes = [s.key for s in graph.STREAMS if participant in s.consumers]
    return produces, consumes


def recovery_keys(key: str) -> tuple[str, str]:
    """The keys zenoh-ext's recovery uses beside a stream's ``key`` (graph.Stream
    .recovered): its publishers' (heartbeats, the cache's queryable and its replies) and
    all of it (the subscribers' queries)."""
    return f"{key}/@adv/pub/**", f"{key}/@adv/**"


def _recovery_rules(name: str, produced: list[str], consumed: list[str]) -> list[dict[str, Any]]:
    """A participant's rights in the recovery of the recovered streams it produces (its
    cache: heartbeats out, queries in, replies out) and consumes (heartbeats in, queries
    out, replies in): nobody but a stream's producer answers for its records."""
    out_pub = [recovery_keys(k)[0] for k in produced]
    in_pub = [recovery_keys(k)[0] for k in consumed]
    rules = []
    if out_pub:
        rules += [
            _rule(f"{name}-keeps", ["put", "declare_queryable", "reply"], "ingress",
                  out_pub + produced),
            _rule(f"{name}-is-asked", ["query", "declare_subscriber"], "egress",
                  [recovery_keys(k)[1] for k in produced]),
        ]  # fmt: skip
    if in_pub:
        rules += [
            _rule(f"{name}-asks", ["query", "declare_subscriber"], "ingress",
                  [recovery_keys(k)[1] for k in consumed]),
            _rule(f"{name}-is-answered", ["put", "declare_queryable", "reply"], "egress",
                  in_pub + consumed),
        ]  # fmt: skip
    return rules


def _rule(rule_id: str, messages: list[str], flow: str, keys: Iterable[str]) -> dict[str, Any]:
    return {
        "id": rule_id,
        "messages": messages,
        "flows": [flow],
        "permission": "allow",
        "key_exprs": sorted(set(keys)),
    }


def participant_robots(name: str, robot_ids: Sequence[str]) -> tuple[str, tuple[str, ...]]:
    """The service whose rights ``name`` has and the robots it acts for in a run of
    ``robot_ids``: a per-robot service's instance (``plant-arm1``, graph.instance_name),
    or the router or observer of one robot's site (graph.router_instance), its own robot;
    any other participant every robot."""
    role, robot = graph.role_of(name), graph.robot_of(name)
    per_robot = role in graph.PER_ROBOT or role in graph.ROUTERS or role in OBSERVERS
    if per_robot and robot in robot_ids:
        return role, (robot,)
    return name, tuple(robot_ids)


def access_control(
    credentials: Mapping[str, Credentials], robot_ids: Sequence[str], *, tls: bool = False
) -> dict[str, Any]:
    """Zenoh's ``access_control`` section for a run of ``credentials``' participants and
    the robots ``robot_ids`` (each one's keys under ``teleop/<robot_id>/``).

    Rules are written from the point of view of a process looking at one peer (the
    subject): *ingress* is what the peer sends it, *egress* what it sends the peer. A
    peer may send the puts of the streams it produces and the subscriptions of those it
    consumes, and receive the converse; it may declare its own tokens and watch all; all
    of it under the keys of the robots it acts for (:func:`participant_robots`).
    A peer is recognised by its Zenoh id and, with ``tls``, also by its certificate's
    common name (the participant's name) in the same subject: both must match.
    """
    prefixes = [f"{ROOT}/{robot_id}" for robot_id in robot_ids]
    tokens = [
        f"{p}/{kind}/*"
        for p in prefixes
        for kind in (ALIVE_TOKEN, READY_TOKEN, PROTOCOL_TOKEN, RELEASED_TOKEN)
    ]
    recovered = {s.key for s in graph.STREAMS if s.recovered}
    rules, subjects, policies = [], [], []
    for name, cred in credentials.items():
        mine = _participant_rules(name, robot_ids, tokens, recovered)
        rules += mine
        if tls:  # both authenticated by TLS together: the name and this session
            mine_subjects = [
                {"id": f"{name}-by-cert", "cert_common_names": [name], "zids": [cred.zid]}
            ]
        else:
            mine_subjects = [{"id": f"{name}-by-zid", "zids": [cred.zid]}]
        subjects += mine_subjects
        policies.append(
            {
                "id": name,
                "rules": [rule["id"] for rule in mine],
                "subjects": [subject["id"] for subject in mine_subjects],
            }
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _participant_rules(
    name: str, robot_ids: Sequence[str], tokens: list[str], recovered: set[str]
) -> list[dict[str, Any]]:
    """The rules of one participant ``name``: its tokens, the puts and subscriptions of
    the streams its role produces and consumes, the queries that recover ``recovered``
    streams, under the keys of the robots it acts for; a router also forwards the other
    sites' ``tokens``."""
    role, robots = participant_robots(name, robot_ids)
    own = [f"{ROOT}/{robot_id}" for robot_id in robots]
    produces, consumes = rights(role)
    produced = [f"{p}/{key}" for p in own for key in produces]
    consumed = [f"{p}/{key}" for p in own for key in consumes]
    own_tokens = [f"{p}/{kind}/{graph.role_of(role)}" for p in own
                  for kind in (ALIVE_TOKEN, READY_TOKEN)]  # fmt: skip
    # The version this stack speaks, and no other: a client that reads it can trust it.
    own_tokens += [f"{p}/{PROTOCOL_TOKEN}/{PROTOCOL_VERSION}" for p in own]
    if role == LAUNCHER:  # it alone releases a lockstep plant held at a fault's instant
        own_tokens += [f"{p}/{RELEASED_TOKEN}/*" for p in own]
    mine = [
        _rule(f"{name}-tokens", ["liveliness_token"], "ingress", own_tokens),
        _rule(f"{name}-peer-tokens", ["liveliness_token"], "egress", tokens),
        _rule(f"{name}-watch-in", _LIVELINESS_WATCH, "ingress", tokens),
        _rule(f"{name}-watch-out", _LIVELINESS_WATCH, "egress", tokens),
    ]
    if produced:
        mine += [
            _rule(f"{name}-publishes", ["put"], "ingress", produced),
            _rule(f"{name}-is-subscribed", ["declare_subscriber"], "egress", produced),
        ]
    if consumed:
        mine += [
            _rule(f"{name}-subscribes", ["declare_subscriber"], "ingress", consumed),
            _rule(f"{name}-receives", ["put"], "egress", consumed),
        ]
    mine += _recovery_rules(
        name,
        [k for k in produced if k.split("/", 2)[2] in recovered],
        [k for k in consumed if k.split("/", 2)[2] in recovered],
    )
    if graph.is_router(name):  # forwards the other sites' tokens
        mine.append(_rule(f"{name}-forwards-tokens", ["liveliness_token"], "ingress", tokens))
    return mine


def write_private(path: Path, text: str) -> None:
    """Write ``text`` to a file only this user can read, from its creation on."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.chmod(path, 0o600)  # an existing file keeps its mode through O_CREAT


def _write_certificate(directory: Path, name: str, issued: Issued) -> dict[str, Any]:
    """``name``'s certificate and key in ``directory`` (mode 0600 each), beside the run's
    :data:`CA_FILE`; returns its Zenoh TLS file settings."""
    certificate, key = (
        directory / (name + CERTIFICATE_SUFFIX),
        directory / (name + PRIVATE_KEY_SUFFIX),
    )
    write_private(certificate, issued.certificate_pem.decode())
    write_private(key, issued.private_key_pem.decode())
    return {
        "root_ca_certificate": str(directory / CA_FILE),
        "listen_certificate": str(certificate),
        "listen_private_key": str(key),
        "connect_certificate": str(certificate),
        "connect_private_key": str(key),
        "enable_mtls": True,
    }


def write_run_certificates(
    directory: Path,
    participants: Sequence[str],
    addresses: Mapping[str, Sequence[str]] | None = None,
) -> dict[str, dict[str, Any]]:
    """A fresh certificate authority's certificate (:data:`CA_FILE`) and one certificate
    and private key per participant in ``directory`` (mode 0600 each; the authority's
    own key is never written), valid on loopback and at the participant's ``addresses``
    (a site's router); returns each participant's Zenoh TLS file settings."""
    from teleop.bus.tls import RunAuthority

    authority = RunAuthority()
    write_private(directory / CA_FILE, authority.certificate_pem.decode())
    addresses = addresses or {}
    return {
        name: _write_certificate(directory, name, authority.issue(name, addresses.get(name, ())))
        for name in participants
    }


def _private_directory(directory: Path) -> Path:
    directory = Path(directory).absolute()
    directory.mkdir(parents=True, exist_ok=True)
    os.chmod(directory, 0o700)
    return directory


def write_run_credentials(
    directory: Path,
    participants: Sequence[str],
    robot_ids: Sequence[str],
    *,
    tls: bool = False,
    addresses: Mapping[str, Sequence[str]] | None = None,
) -> dict[str, Path]:
    """Fresh identities for ``participants`` in ``directory`` (made mode 0700), one file
    per participant (mode 0600) with its name, Zenoh id and the run's access-control
    list; returns the files by name (each one ``bus.credentials_file`` of its
    participant).

    ``tls``: the run's certificates (:func:`write_run_certificates`; ``addresses``: where
    a participant listens besides loopback), each file naming its participant's own; no
    password anywhere. Without: a password per participant and the run's dictionary
    (:data:`PASSWORDS_FILE`), named in the file of every participant that accepts links
    (all but the observers)."""
    if isinstance(robot_ids, str):
        raise TypeError(f"robot_ids: a sequence of robot ids, not the string {robot_ids!r}")
    directory = _private_directory(directory)
    credentials = {name: Credentials.generate(name) for name in participants}
    acl = access_control(credentials, robot_ids, tls=tls)
    own_secret: dict[str, dict[str, Any]]
    if tls:
        certificates = write_run_certificates(directory, list(credentials), addresses)
        own_secret = {name: {"tls": certificates[name]} for name in credentials}
    else:
        dictionary = directory / PASSWORDS_FILE
        lines = "".join(f"{c.user}:{c.password}\n" for c in credentials.values())
        write_private(dictionary, lines)
        own_secret = {
            name: {"password": cred.password}
            | ({} if name in OBSERVERS else {"dictionary_file": str(dictionary)})
            for name, cred in credentials.items()
        }
    files = {}
    for name, cred in credentials.items():
        path = directory / f"{name}.json"
        content = {"user": cred.user, "zid": cred.zid, **own_secret[name], "access_control": acl}
        write_private(path, json.dumps(content, indent=1))
        files[name] = path
    return files


def export_identities(files: Mapping[str, Path]) -> dict[str, Any]:
    """The identities of ``files`` (participants' credentials files of a TLS run) as one
    JSON-able record, their certificates and keys and the authority's certificate
    inline: what another host needs to take part in the run as those participants
    (:func:`import_identities`). It holds private keys: keep it private."""
    exported: dict[str, Any] = {"participants": {}}
    for name, path in files.items():
        content = json.loads(Path(path).read_text())
        if "tls" not in content:
            raise ValueError(f"{path}: no certificate (a run across hosts needs bus.tls)")
        tls = content["tls"]
        exported["ca_pem"] = Path(tls["root_ca_certificate"]).read_text()
        exported["access_control"] = content["access_control"]
        exported["participants"][name] = {
            "zid": content["zid"],
            "certificate_pem": Path(tls["connect_certificate"]).read_text(),
            "private_key_pem": Path(tls["connect_private_key"]).read_text(),
        }
    return exported


def import_identities(directory: Path, exported: Mapping[str, Any]) -> dict[str, Path]:
    """Write the identities of :func:`export_identities` into ``directory`` (mode 0700,
    files 0600) as this host's credentials files; returns them by name. KeyError or
    ValueError on a malformed record."""
    from teleop.bus.tls import Issued

    directory = _private_directory(directory)
    write_private(directory / CA_FILE, str(exported["ca_pem"]))
    files = {}
    for name, identity in exported["participants"].items():
        if not name or not set(name) <= _NAME_ALPHABET:
            raise ValueError(f"participant name {name!r}")
        issued = Issued(
            str(identity["certificate_pem"]).encode(), str(identity["private_key_pem"]).encode()
        )
        content = {
            "user": name,
            "zid": str(identity["zid"]),
            "tls": _write_certificate(directory, name, issued),
            "access_control": exported["access_control"],
        }
        files[name] = directory / f"{name}.json"
        write_private(files[name], json.dumps(content, indent=1))
    return files


def participant_zids(credentials_file: Path) -> frozenset[str]:
    """The Zenoh ids (lower-case hex) of the run's participants, from the access list of
    a participant's credentials file."""
    acl = json.loads(Path(credentials_file).read_text())["access_control"]
    return frozenset(zid.lower() for subject in acl["subjects"] for zid in subject["zids"])


def strangers(linked: Iterable[object], participants: Collection[str]) -> list[str]:
    """The Zenoh ids among ``linked`` (a session's ``info.peers_zid()``) that are no
    participant of the run (:func:`participant_zids`), in order."""
    return [zid for zid in map(str, linked) if zid.lower() not in participants]


def zenoh_entries(credentials_file: Path) -> dict[str, Any]:
    """The Zenoh config entries (path -> value) a participant's credentials file sets:
    its id, the access-control list and either its certificate files (under
    :data:`TLS_CONFIG`) or its user/password (with the run's dictionary where it
    accepts links)."""
    content = json.loads(Path(credentials_file).read_text())
    entries: dict[str, Any] = {"id": content["zid"], "access_control": content["access_control"]}
    if "tls" in content:
        entries |= {f"{TLS_CONFIG}/{key}": value for key, value in content["tls"].items()}
    else:
        usrpwd = {"user": content["user"], "password": content["password"]}
        if "dictionary_file" in content:
            usrpwd["dictionary_file"] = content["dictionary_file"]
        entries["transport/auth/usrpwd"] = usrpwd
    return entries

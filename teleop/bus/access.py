"""Who may say what on a stack's bus: per-run credentials and an access-control list,
both derived from the one description of the graph (:mod:`teleop.bus.graph`).

A launcher (``teleop run``, ``teleop up``, ``teleop latency``) gives every process of the
run (every service, the launcher itself, an outside client) a name, a random password
and a random Zenoh id, written to files only its user can read
(:func:`write_run_credentials`). :func:`teleop.bus.session.open_session` loads a
process's file (``bus.credentials_file``) into its Zenoh config:

- Authentication (Zenoh's user/password): a link is accepted only from a process that
  presents a user and password of the run's dictionary. A session of another stack,
  another user, or anyone without this run's files cannot link at all.
- Access control, default deny, the same list in every process: a participant may
  publish only the streams the graph lists it as producing, subscribe only to those it
  consumes, and declare only its own liveliness tokens. So only the controller's
  commands reach the plant, only the plant's states and events the others, and so on.

Zenoh's user/password authenticates the process that opens a link to the one that
accepts it, not the other way round. Each process therefore matches a peer by either:
its authenticated user name (links it accepted) or its Zenoh id (links it opened: the
ids are per-run secrets in the same 0600 files, so a process squatting on a port
cannot pass for a service of the run). See docs/protocol.md, "Access control".

With ``bus.tls`` the run also gets a certificate authority and one certificate per
participant (:mod:`teleop.bus.tls`): every link is mutual TLS, and a peer also matches
its policy by its certificate's common name, which both ends of a link authenticate.
"""

from __future__ import annotations

import json
import os
import secrets
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from teleop.bus import graph
from teleop.bus.graph import ALIVE_TOKEN, READY_TOKEN, ROOT
from teleop.bus.tls import RunAuthority

# The launcher's own session (teleop run): it consumes the streams the graph lists for
# "launcher" and declares its tokens under this name.
LAUNCHER = "launcher"
# A read-only participant every launcher adds: it may subscribe to every stream and
# publish nothing (a user's own plotting script, a test watching the bus).
OBSERVER = "observer"
# The run's dictionary of user:password lines (every process accepts links from these).
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

    user: str
    password: str
    zid: str  # Zenoh id, 32 hex digits, the first not 0 (Zenoh refuses leading zeros)

    @classmethod
    def generate(cls, name: str) -> Credentials:
        if not name or not set(name) <= _NAME_ALPHABET:
            raise ValueError(f"participant name {name!r}: lower-case letters, digits, _ and -")
        return cls(name, secrets.token_hex(16), new_zid())


def new_zid() -> str:
    """A random Zenoh id: 32 hex digits, the first not 0 (Zenoh refuses leading zeros)."""
    return format(secrets.randbits(127) | 1 << 127, "032x")


def rights(participant: str) -> tuple[list[str], list[str]]:
    """Keys (after ``teleop/<robot>/``) the graph lets ``participant`` publish and
    subscribe to (:data:`OBSERVER`: none, and every stream)."""
    if participant == OBSERVER:
        return [], [s.key for s in graph.STREAMS]
    produces = [s.key for s in graph.STREAMS if participant in s.producers]
    consumes = [s.key for s in graph.STREAMS if participant in s.consumers]
    return produces, consumes


def _rule(rule_id: str, messages: list[str], flow: str, keys: Iterable[str]) -> dict[str, Any]:
    return {
        "id": rule_id,
        "messages": messages,
        "flows": [flow],
        "permission": "allow",
        "key_exprs": sorted(set(keys)),
    }


def access_control(
    credentials: Mapping[str, Credentials], robot_id: str, *, tls: bool = False
) -> dict[str, Any]:
    """Zenoh's ``access_control`` section for a run of ``credentials``' participants.

    Rules are written from the point of view of a process looking at one peer (the
    subject): *ingress* is what the peer sends it, *egress* what it sends the peer. A
    peer may send the puts of the streams it produces and the subscriptions of those it
    consumes, and receive the converse; it may declare its own tokens and watch all.
    A peer is recognised by its user name or its Zenoh id and, with ``tls``, by its
    certificate's common name (the participant's name).
    """
    prefix = f"{ROOT}/{robot_id}"
    tokens = [f"{prefix}/{ALIVE_TOKEN}/*", f"{prefix}/{READY_TOKEN}/*"]
    rules, subjects, policies = [], [], []
    for name, cred in credentials.items():
        produces, consumes = rights(name)
        produced = [f"{prefix}/{key}" for key in produces]
        consumed = [f"{prefix}/{key}" for key in consumes]
        own_tokens = [f"{prefix}/{ALIVE_TOKEN}/{name}", f"{prefix}/{READY_TOKEN}/{name}"]
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
        rules += mine
        mine_subjects = [
            {"id": f"{name}-by-user", "usernames": [cred.user]},
            {"id": f"{name}-by-zid", "zids": [cred.zid]},
        ]
        if tls:
            mine_subjects.append({"id": f"{name}-by-cert", "cert_common_names": [name]})
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


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to a file only this user can read, from its creation on."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.chmod(path, 0o600)  # an existing file keeps its mode through O_CREAT


def write_run_certificates(
    directory: Path, participants: Sequence[str]
) -> dict[str, dict[str, str]]:
    """A fresh certificate authority's certificate (:data:`CA_FILE`) and one certificate
    and private key per participant in ``directory`` (mode 0600 each; the authority's
    own key is never written); returns each participant's Zenoh TLS file settings."""
    authority = RunAuthority()
    ca_file = directory / CA_FILE
    _write_private(ca_file, authority.certificate_pem.decode())
    settings = {}
    for name in participants:
        issued = authority.issue(name)
        certificate, key = (
            directory / (name + CERTIFICATE_SUFFIX),
            directory / (name + PRIVATE_KEY_SUFFIX),
        )
        _write_private(certificate, issued.certificate_pem.decode())
        _write_private(key, issued.private_key_pem.decode())
        settings[name] = {
            "root_ca_certificate": str(ca_file),
            "listen_certificate": str(certificate),
            "listen_private_key": str(key),
            "connect_certificate": str(certificate),
            "connect_private_key": str(key),
            "enable_mtls": True,
        }
    return settings


def write_run_credentials(
    directory: Path, participants: Sequence[str], robot_id: str, *, tls: bool = False
) -> dict[str, Path]:
    """Fresh credentials for ``participants`` in ``directory`` (made mode 0700): the
    run's password dictionary and one file per participant (mode 0600) with its user,
    password, Zenoh id and the run's access-control list; returns the files by name
    (each one ``bus.credentials_file`` of its participant). ``tls``: also the run's
    certificates (:func:`write_run_certificates`), named in each file."""
    directory = Path(directory).absolute()
    directory.mkdir(parents=True, exist_ok=True)
    os.chmod(directory, 0o700)
    credentials = {name: Credentials.generate(name) for name in participants}
    dictionary = directory / PASSWORDS_FILE
    _write_private(dictionary, "".join(f"{c.user}:{c.password}\n" for c in credentials.values()))
    acl = access_control(credentials, robot_id, tls=tls)
    certificates = write_run_certificates(directory, list(credentials)) if tls else {}
    files = {}
    for name, cred in credentials.items():
        path = directory / f"{name}.json"
        content = {**asdict(cred), "dictionary_file": str(dictionary), "access_control": acl}
        if tls:
            content["tls"] = certificates[name]
        _write_private(path, json.dumps(content, indent=1))
        files[name] = path
    return files


def zenoh_entries(credentials_file: Path) -> dict[str, Any]:
    """The Zenoh config entries (path -> value) a participant's credentials file sets:
    its id, its user/password with the run's dictionary, the access-control list and,
    in a TLS run, its certificate files (under :data:`TLS_CONFIG`)."""
    content = json.loads(Path(credentials_file).read_text())
    tls = {f"{TLS_CONFIG}/{key}": value for key, value in content.get("tls", {}).items()}
    return {
        **tls,
        "id": content["zid"],
        "transport/auth/usrpwd": {
            "user": content["user"],
            "password": content["password"],
            "dictionary_file": content["dictionary_file"],
        },
        "access_control": content["access_control"],
    }

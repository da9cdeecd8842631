"""A run's certificates (teleop.bus.tls) and how the credentials name them
(teleop.bus.access): checked with the cryptography package, no Zenoh."""

from __future__ import annotations

import ipaddress
import json
import stat
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from teleop.bus.access import (
    CA_FILE,
    CERTIFICATE_SUFFIX,
    OBSERVER,
    PASSWORDS_FILE,
    PRIVATE_KEY_SUFFIX,
    TLS_CONFIG,
    write_run_credentials,
    zenoh_entries,
)
from teleop.bus.tls import RunAuthority
from teleop.core.config import load_config

PARTICIPANTS = ["plant", "controller"]


def common_name(certificate: x509.Certificate) -> str:
    return certificate.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value


def test_a_participants_certificate_is_signed_by_its_runs_authority_only():
    authority, other = RunAuthority(), RunAuthority()
    ca = x509.load_pem_x509_certificate(authority.certificate_pem)
    issued = x509.load_pem_x509_certificate(authority.issue("plant").certificate_pem)
    assert common_name(issued) == "plant"
    issued.verify_directly_issued_by(ca)
    with pytest.raises(InvalidSignature):  # same issuer name, another key
        issued.verify_directly_issued_by(x509.load_pem_x509_certificate(other.certificate_pem))
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is True
    assert issued.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is False
    usages = issued.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH} <= set(usages)
    # valid for the address the run's processes dial
    names = issued.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert ipaddress.IPv4Address("127.0.0.1") in names.get_values_for_type(x509.IPAddress)


def test_tls_credentials_name_private_certificate_files_and_the_acl_knows_their_names(
    tmp_path,
):
    directory = tmp_path / "auth"
    files = write_run_credentials(directory, PARTICIPANTS, ("arm0",), tls=True)
    ca = x509.load_pem_x509_certificate((directory / CA_FILE).read_bytes())
    for name in PARTICIPANTS:
        certificate_file = directory / (name + CERTIFICATE_SUFFIX)
        key_file = directory / (name + PRIVATE_KEY_SUFFIX)
        for path in (certificate_file, key_file, directory / CA_FILE):
            assert stat.S_IMODE(path.stat().st_mode) == 0o600
        certificate = x509.load_pem_x509_certificate(certificate_file.read_bytes())
        assert common_name(certificate) == name
        certificate.verify_directly_issued_by(ca)
        entries = zenoh_entries(files[name])
        assert entries[f"{TLS_CONFIG}/enable_mtls"] is True
        assert entries[f"{TLS_CONFIG}/root_ca_certificate"] == str(directory / CA_FILE)
        assert entries[f"{TLS_CONFIG}/listen_certificate"] == str(certificate_file)
        assert entries[f"{TLS_CONFIG}/connect_private_key"] == str(key_file)
    # nothing but certificates and keys of participants: the authority's key is gone
    pem_files = {path.name for path in directory.glob("*.pem")}
    assert pem_files == {CA_FILE} | {
        name + suffix
        for name in PARTICIPANTS
        for suffix in (CERTIFICATE_SUFFIX, PRIVATE_KEY_SUFFIX)
    }
    acl = json.loads(files["plant"].read_text())["access_control"]
    zids = {name: json.loads(files[name].read_text())["zid"] for name in PARTICIPANTS}
    # one subject per participant: its certificate's name and its session's id together
    assert acl["subjects"] == [
        {"id": f"{name}-by-cert", "cert_common_names": [name], "zids": [zids[name]]}
        for name in PARTICIPANTS
    ]
    for policy in acl["policies"]:
        assert policy["subjects"] == [f"{policy['id']}-by-cert"]


def test_each_tls_file_leads_to_its_own_key_and_no_password(tmp_path):
    """What a participant is given (its file and every file it names) holds no secret of
    another: no password, no dictionary, no other participant's key."""
    directory = tmp_path / "auth"
    participants = [*PARTICIPANTS, OBSERVER]
    files = write_run_credentials(directory, participants, ("arm0",), tls=True)
    assert not (directory / PASSWORDS_FILE).exists()
    for name in participants:
        content = json.loads(files[name].read_text())
        assert "password" not in content and "dictionary_file" not in content
        named = {Path(value) for value in content["tls"].values() if isinstance(value, str)}
        assert named == {
            directory / CA_FILE,
            directory / (name + CERTIFICATE_SUFFIX),
            directory / (name + PRIVATE_KEY_SUFFIX),
        }
        ca_text = (directory / CA_FILE).read_text()
        assert "PRIVATE KEY" not in ca_text  # the authority's certificate only
        assert "transport/auth/usrpwd" not in zenoh_entries(files[name])


def test_without_tls_the_observer_is_not_given_the_password_dictionary(tmp_path):
    directory = tmp_path / "auth"
    files = write_run_credentials(directory, [*PARTICIPANTS, OBSERVER], ("arm0",))
    observer = json.loads(files[OBSERVER].read_text())
    assert "dictionary_file" not in observer
    assert "dictionary_file" not in zenoh_entries(files[OBSERVER])["transport/auth/usrpwd"]
    others = [json.loads(files[name].read_text())["password"] for name in PARTICIPANTS]
    assert not any(password in files[OBSERVER].read_text() for password in others)
    # a service accepts links: it checks them against the dictionary
    plant = zenoh_entries(files["plant"])["transport/auth/usrpwd"]
    assert plant["dictionary_file"] == str(directory / PASSWORDS_FILE)
    # known by Zenoh id only: a name alone would let any password holder in, any id
    acl = observer["access_control"]
    assert all(set(subject) == {"id", "zids"} for subject in acl["subjects"])


def test_credentials_without_tls_set_no_tls_entries(tmp_path):
    files = write_run_credentials(tmp_path / "auth", PARTICIPANTS, ("arm0",))
    assert not any(path.startswith(TLS_CONFIG) for path in zenoh_entries(files["plant"]))
    assert list((tmp_path / "auth").glob("*.pem")) == []


def test_tls_is_the_default_and_only_with_the_runs_credentials():
    assert load_config(None, []).bus.mutual_tls is True
    assert load_config(None, ["bus.secure=false"]).bus.mutual_tls is False
    assert load_config(None, ["bus.tls=false"]).bus.mutual_tls is False

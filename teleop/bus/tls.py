"""Per-run certificates for mutual TLS between the processes of a stack (``bus.tls``).

A launcher makes a certificate authority for one run, issues one certificate per
participant (common name = the participant's name, the same name its user/password and
its access-control policy carry) and forgets the authority's private key: nobody, the
launcher included, can issue another certificate this run's processes accept. Each
process then opens and accepts links only over ``tls/`` endpoints, presenting its own
certificate and accepting only peers whose certificate this run's authority signed
(Zenoh's ``enable_mtls``). :mod:`teleop.bus.access` writes the files; nothing here
touches the disk.

Keys are ECDSA P-256 (fast handshakes, accepted by Zenoh's TLS stack, rustls). A
certificate names 127.0.0.1 and ``localhost`` as subject alternative names, so a process
that connects to ``tls/127.0.0.1:PORT`` checks the listener's certificate against the
address it dialled (Zenoh's ``verify_name_on_connect``, on by default).
"""

from __future__ import annotations

import datetime
import ipaddress
from collections.abc import Sequence
from dataclasses import dataclass

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

# How long a run's certificates are valid: a detached stack (teleop up) may run for
# weeks, and a certificate that expires only stops new links (existing ones stay up).
VALIDITY = datetime.timedelta(days=365)
# Start of validity moved back from now, for a peer whose clock is a little behind.
CLOCK_SKEW = datetime.timedelta(minutes=5)
# Addresses a participant's certificate is valid for (every run links over loopback).
LOOPBACK_NAMES: tuple[x509.GeneralName, ...] = (
    x509.IPAddress(ipaddress.IPv4Address("127.0.0.1")),
    x509.DNSName("localhost"),
)
CA_COMMON_NAME = "teleop run CA"


@dataclass(frozen=True)
class Issued:
    """A participant's certificate and private key, PEM."""

    certificate_pem: bytes
    private_key_pem: bytes


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _general_name(address: str) -> x509.GeneralName:
    """An IP address's or a host name's subject alternative name."""
    try:
        return x509.IPAddress(ipaddress.ip_address(address))
    except ValueError:
        return x509.DNSName(address)


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


class RunAuthority:
    """A run's certificate authority, in memory only: issue the participants'
    certificates, keep :attr:`certificate_pem` (every process's root of trust), then
    drop the object (its private key is never written)."""

    def __init__(self) -> None:
        self._key = _new_key()
        now = datetime.datetime.now(datetime.UTC)
        self._name = _name(CA_COMMON_NAME)
        public_key = self._key.public_key()
        self._certificate = (
            x509.CertificateBuilder()
            .subject_name(self._name)
            .issuer_name(self._name)
            .public_key(public_key)
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - CLOCK_SKEW)
            .not_valid_after(now + VALIDITY)
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(
                x509.KeyUsage(
                    digital_signature=False,
                    content_commitment=False,
                    key_encipherment=False,
                    data_encipherment=False,
                    key_agreement=False,
                    key_cert_sign=True,
                    crl_sign=True,
                    encipher_only=False,
                    decipher_only=False,
                ),
                critical=True,
            )
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(public_key), critical=False)
            .sign(self._key, hashes.SHA256())
        )

    @property
    def certificate_pem(self) -> bytes:
        return self._certificate.public_bytes(serialization.Encoding.PEM)

    def issue(self, common_name: str, addresses: Sequence[str] = ()) -> Issued:
        """A fresh key and a certificate for ``common_name``, good for both ends of a
        link (server and client authentication) on loopback and at ``addresses`` (IP
        addresses or host names: where a site's router is reached from another host)."""
        names = [*LOOPBACK_NAMES, *map(_general_name, addresses)]
        key = _new_key()
        now = datetime.datetime.now(datetime.UTC)
        certificate = (
            x509.CertificateBuilder()
            .subject_name(_name(common_name))
            .issuer_name(self._name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - CLOCK_SKEW)
            .not_valid_after(now + VALIDITY)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.ExtendedKeyUsage(
                    [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
                ),
                critical=False,
            )
            .add_extension(x509.SubjectAlternativeName(names), critical=False)
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_public_key(self._key.public_key()),
                critical=False,
            )
            .sign(self._key, hashes.SHA256())
        )
        return Issued(certificate.public_bytes(serialization.Encoding.PEM), _key_pem(key))

"""Certificates for the job engine's TLS (`fidotrack engine-certs`): an authority of the
deployment's own and a certificate per role (scheduler, worker, web), each signed by it.

Dask checks that a peer's certificate was signed by the authority, not the name in it
(peers are often known by address), so any certificate the authority signed is trusted
for every role: its key signs no more than these, and is best kept off the engine's
machines once they are made."""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from pathlib import Path

#: The roles a certificate is made for, and the settings each process is given.
ROLES = ("scheduler", "worker", "web")
CA_NAME = "ca"
#: How long the certificates are valid by default (days).
DEFAULT_DAYS = 825


@dataclass(frozen=True)
class Issued:
    """The files made: the authority's certificate and key, and each role's pair."""

    ca_file: Path
    ca_key_file: Path
    certs: dict[str, tuple[Path, Path]]


def _write(path: Path, data: bytes, mode: int) -> None:
    # (Created with its mode, never readable by others even for a moment; never overwriting.)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    with os.fdopen(fd, "wb") as out:
        out.write(data)


def _issued(out: Path) -> Issued:
    return Issued(out / f"{CA_NAME}.pem", out / f"{CA_NAME}-key.pem",
                  {role: (out / f"{role}.pem", out / f"{role}-key.pem") for role in ROLES})


def make_engine_certs(out: Path, days: int = DEFAULT_DAYS, *, if_missing: bool = False,
                      name: str = "fidotrack job engine") -> Issued:
    """Write an authority (``ca.pem``, ``ca-key.pem``) and, for each role, ``ROLE.pem`` and
    ``ROLE-key.pem`` that it signed, into `out` (made if missing); keys readable by their
    owner only. FileExistsError when one of the files is already there; with
    `if_missing`, a folder that holds them all is left as it is."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    issued = _issued(out)
    paths = [issued.ca_file, issued.ca_key_file, *(p for pair in issued.certs.values() for p in pair)]
    out.mkdir(parents=True, exist_ok=True)
    existing = [p.name for p in paths if p.exists()]
    if if_missing and len(existing) == len(paths):
        return issued
    if existing:
        raise FileExistsError(f"{out} already holds {', '.join(existing)}: give an empty folder")
    now = datetime.datetime.now(datetime.timezone.utc)
    valid = {"not_valid_before": now - datetime.timedelta(minutes=5),
             "not_valid_after": now + datetime.timedelta(days=days)}

    def pem_key(key: ec.EllipticCurvePrivateKey) -> bytes:
        return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                 serialization.NoEncryption())

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"{name} authority")])
    ca_cert = (x509.CertificateBuilder(subject_name=ca_name, issuer_name=ca_name, public_key=ca_key.public_key(),
                                       serial_number=x509.random_serial_number(), **valid)
               .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
               .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                            data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                            crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
               .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
               .sign(ca_key, hashes.SHA256()))
    _write(issued.ca_file, ca_cert.public_bytes(serialization.Encoding.PEM), 0o644)
    _write(issued.ca_key_file, pem_key(ca_key), 0o600)
    for role, (cert_file, key_file) in issued.certs.items():
        key = ec.generate_private_key(ec.SECP256R1())
        # Each process both listens and connects: a server's and a client's certificate at once.
        subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"{name} {role}")])
        cert = (x509.CertificateBuilder(subject_name=subject, issuer_name=ca_name, public_key=key.public_key(),
                                        serial_number=x509.random_serial_number(), **valid)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                      ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
                .add_extension(x509.SubjectAlternativeName([x509.DNSName(role)]), critical=False)
                .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
                .sign(ca_key, hashes.SHA256()))
        _write(cert_file, cert.public_bytes(serialization.Encoding.PEM), 0o644)
        _write(key_file, pem_key(key), 0o600)
    return issued

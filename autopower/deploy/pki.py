"""The team's certificate authority and the key + certificate of each node (mutual TLS).

One CA per team, made here; every node (robots, base station, the operator's CLI) gets an EC
P-256 key and a certificate signed by it with CN = the node's name (the identity Zenoh's access
control sees) and a SAN for each address others connect to (Zenoh checks it on connect).
Private keys are written 0600 into a 0700 directory, never printed and never logged: the only
thing this module ever says about a key is its path.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
from dataclasses import dataclass
from pathlib import Path

from autopower.errors import AutoPowerError

CA_CERT = "ca.pem"
CA_KEY = "ca.key"
VALID_DAYS = 825  # what browsers still accept for a leaf; a lab fleet renews with `deploy init`


@dataclass(frozen=True)
class NodeIdentity:
    """Where one node's TLS material is (paths only: nothing here holds key bytes)."""

    name: str
    ca: Path
    cert: Path
    key: Path


def _write_private(path: Path, data: bytes) -> None:
    """Create ``path`` with mode 0600 from the start (no window where it is world-readable)."""
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.unlink()
    except FileNotFoundError:
        pass
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(tmp, 0o600)  # in case a umask or ACL widened it
    tmp.replace(path)


def _write_public(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.chmod(tmp, 0o644)
    tmp.replace(path)


def _name(cn: str):
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "AutoPower"),
                      x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _san(addresses) -> list:
    from cryptography import x509

    out = []
    for addr in dict.fromkeys(addresses):
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(addr)))
        except ValueError:
            out.append(x509.DNSName(addr))
    return out


class TeamCA:
    """A team's certificate authority, kept in one directory (``ca.pem`` public, ``ca.key`` 0600)."""

    def __init__(self, directory: Path, key, cert):
        self.directory = Path(directory)
        self._key = key
        self._cert = cert

    @property
    def cert_path(self) -> Path:
        return self.directory / CA_CERT

    @classmethod
    def create(cls, directory: Path, team: str) -> "TeamCA":
        """A new CA for ``team`` written into ``directory`` (an existing one is replaced)."""
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec

        directory = Path(directory)
        key = ec.generate_private_key(ec.SECP256R1())
        now = datetime.datetime.now(datetime.timezone.utc)
        name = _name(f"AutoPower team {team} CA")
        cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
                .public_key(key.public_key()).serial_number(x509.random_serial_number())
                .not_valid_before(now - datetime.timedelta(minutes=5))
                .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
                .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
                .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False,
                                             key_encipherment=False, data_encipherment=False, key_agreement=False,
                                             key_cert_sign=True, crl_sign=True, encipher_only=False,
                                             decipher_only=False), critical=True)
                .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
                .sign(key, hashes.SHA256()))
        _write_private(directory / CA_KEY, key.private_bytes(serialization.Encoding.PEM,
                                                             serialization.PrivateFormat.PKCS8,
                                                             serialization.NoEncryption()))
        _write_public(directory / CA_CERT, cert.public_bytes(serialization.Encoding.PEM))
        return cls(directory, key, cert)

    @classmethod
    def load(cls, directory: Path) -> "TeamCA":
        from cryptography import x509
        from cryptography.hazmat.primitives import serialization

        directory = Path(directory)
        try:
            key = serialization.load_pem_private_key((directory / CA_KEY).read_bytes(), password=None)
            cert = x509.load_pem_x509_certificate((directory / CA_CERT).read_bytes())
        except FileNotFoundError as exc:
            raise AutoPowerError(f"no team CA in {directory} ({exc.filename} is missing); "
                                 "create one with `autopower deploy init`") from None
        except ValueError as exc:
            raise AutoPowerError(f"the team CA in {directory} cannot be read ({exc}); "
                                 "recreate it with `autopower deploy init`") from None
        return cls(directory, key, cert)

    def issue(self, name: str, addresses, out_dir: Path) -> NodeIdentity:
        """Key + certificate for node ``name`` (CN) reachable at ``addresses`` (SAN), into ``out_dir``."""
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID

        out_dir = Path(out_dir)
        key = ec.generate_private_key(ec.SECP256R1())
        now = datetime.datetime.now(datetime.timezone.utc)
        builder = (x509.CertificateBuilder().subject_name(_name(name)).issuer_name(self._cert.subject)
                   .public_key(key.public_key()).serial_number(x509.random_serial_number())
                   .not_valid_before(now - datetime.timedelta(minutes=5))
                   .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
                   .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                   .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                         ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
                   .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(self._key.public_key()),
                                  critical=False))
        san = _san(addresses)
        if san:
            builder = builder.add_extension(x509.SubjectAlternativeName(san), critical=False)
        cert = builder.sign(self._key, hashes.SHA256())
        identity = NodeIdentity(name=name, ca=out_dir / CA_CERT, cert=out_dir / f"{name}.pem",
                                key=out_dir / f"{name}.key")
        _write_private(identity.key, key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                       serialization.NoEncryption()))
        _write_public(identity.cert, cert.public_bytes(serialization.Encoding.PEM))
        if identity.ca != self.cert_path:
            _write_public(identity.ca, self._cert.public_bytes(serialization.Encoding.PEM))
        return identity


def common_name(cert_path: Path) -> str:
    """The CN of a certificate file (the identity access control sees)."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    cert = x509.load_pem_x509_certificate(Path(cert_path).read_bytes())
    return cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value


def identity_in(directory, node: str):
    """The TLS files of ``node`` in ``directory`` (ca.pem, NODE.pem, NODE.key), checked to exist."""
    from autopower.runtime.bus import TlsFiles

    directory = Path(directory)
    files = TlsFiles(ca=str(directory / CA_CERT), cert=str(directory / f"{node}.pem"),
                     key=str(directory / f"{node}.key"))
    for path in (files.ca, files.cert, files.key):
        if not Path(path).is_file():
            raise AutoPowerError(f"{path} is missing: {directory} holds no TLS identity for {node!r}")
    return files

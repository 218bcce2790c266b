"""End-to-end signatures: who wrote a message that crossed other robots, or that claims a sender.

Zenoh's mutual TLS authenticates each *link*, and its access control judges the key a peer puts
on; neither says who wrote a payload that a robot relays for another node, nor who cast a
subgroup vote (every robot may put on the subgroup key). So the author signs those messages with
its node's private key (EC P-256, the key of its TLS identity, issued by the team CA) and attaches
its certificate; the receiver checks that certificate against the team CA, takes the signer's
name from its common name, verifies the signature and compares the name with what the message
claims (the relay's origin, the voter, the round's leader). A message that fails is dropped and
counted. A certificate is verified once and remembered (by its bytes), so a steady stream costs
one ECDSA verification per message.

`--insecure` teams have no keys: nothing is signed, nothing is checked, and they say so.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from autopower.errors import ProtocolError
from autopower.protocol import encode

log = logging.getLogger(__name__)

SIGNATURE_FIELDS = ("signer_cert", "signature")  # every signed message has these two fields


class Signing:
    """This node's signing key and certificate, and the team CA that vouches for the others'."""

    def __init__(self, node: str, key, cert_der: bytes, ca_cert):
        self.node = node
        self._key = key  # never logged, never printed
        self.cert_der = cert_der
        self._ca = ca_cert
        self._known: dict[bytes, str] = {cert_der: node}  # verified certificate -> its common name
        self.verified = 0
        self.forged = 0

    @classmethod
    def load(cls, node: str, ca: str | Path, cert: str | Path, key: str | Path) -> "Signing":
        from cryptography import x509
        from cryptography.hazmat.primitives import serialization

        certificate = x509.load_pem_x509_certificate(Path(cert).read_bytes())
        private = serialization.load_pem_private_key(Path(key).read_bytes(), password=None)
        return cls(node, private, certificate.public_bytes(serialization.Encoding.DER),
                   x509.load_pem_x509_certificate(Path(ca).read_bytes()))

    # ---- signing ---------------------------------------------------------------------------------
    def sign(self, msg, **canonical):
        """``msg`` with our certificate and a signature over its encoding (``canonical`` fields
        replaced first: those a forwarder changes on the way, e.g. a relay's hop)."""
        from cryptography.hazmat.primitives import hashes
        from cryptography.hazmat.primitives.asymmetric import ec

        unsigned = dataclasses.replace(msg, signer_cert=self.cert_der, signature=b"")
        data = encode(dataclasses.replace(unsigned, **canonical)) if canonical else encode(unsigned)
        return dataclasses.replace(unsigned, signature=self._key.sign(data, ec.ECDSA(hashes.SHA256())))

    # ---- verifying -------------------------------------------------------------------------------
    def signer(self, msg, **canonical) -> str:
        """The name of the team member who signed ``msg``; ProtocolError if nobody of the team did."""
        from cryptography.exceptions import InvalidSignature
        from cryptography.hazmat.primitives import hashes
        from cryptography.hazmat.primitives.asymmetric import ec

        if not msg.signature or not msg.signer_cert:
            raise ProtocolError(f"an unsigned {type(msg).__name__}")
        name, cert = self._member(msg.signer_cert)
        data = encode(dataclasses.replace(msg, signature=b"", **canonical))
        try:
            cert.public_key().verify(msg.signature, data, ec.ECDSA(hashes.SHA256()))
        except InvalidSignature:
            raise ProtocolError(f"a {type(msg).__name__} whose signature does not match {name}'s key") from None
        self.verified += 1
        return name

    def _member(self, der: bytes):
        import datetime

        from cryptography import x509
        from cryptography.exceptions import InvalidSignature
        from cryptography.x509.oid import NameOID

        try:
            cert = x509.load_der_x509_certificate(der)
        except ValueError:
            raise ProtocolError("a signer certificate that does not parse") from None
        name = self._known.get(der)
        if name is not None:
            return name, cert
        try:
            cert.verify_directly_issued_by(self._ca)  # issuer name and the CA's signature
        except (InvalidSignature, ValueError, TypeError) as exc:
            raise ProtocolError(f"a signer certificate not issued by the team CA ({type(exc).__name__})") from None
        now = datetime.datetime.now(datetime.timezone.utc)
        if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
            raise ProtocolError("an expired (or not yet valid) signer certificate")
        names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
        if len(names) != 1:
            raise ProtocolError("a signer certificate without one common name")
        name = str(names[0].value)
        if len(self._known) < 1024:  # a team has a handful of members; never grow without bound
            self._known[der] = name
        return name, cert

    def check(self, msg, claimed: str, what: str, **canonical) -> bool:
        """True if ``claimed`` signed ``msg``; otherwise log, count a forgery and return False."""
        try:
            name = self.signer(msg, **canonical)
        except ProtocolError as exc:
            self.forged += 1
            log.warning("%s: dropped %s claiming %s: %s", self.node, what, claimed, exc)
            return False
        if name != claimed:
            self.forged += 1
            log.warning("%s: dropped %s claiming %s, signed by %s", self.node, what, claimed, name)
            return False
        return True


def load_signing(node: str, tls) -> Signing | None:
    """The node's `Signing` from its TLS files (`runtime.bus.TlsFiles`), or None for an insecure team."""
    if tls is None:
        log.warning("%s: --insecure: relayed messages and subgroup votes are not signed; a relaying robot "
                    "could forge their origin", node)
        return None
    return Signing.load(node, tls.ca, tls.cert, tls.key)

"""The OPC UA front-end's certificates and trust lists, kept as files (docs/opcua.md "Security").

``opcua: pki`` (default ``opcua-pki`` beside the configuration file)::

    own/cert.der            the server's application certificate, made at the first start
    own/private/key.pem     its private key (mode 0600, in a 0700 folder)
    trusted/                client application certificates (or their CAs) that are let in
    rejected/               certificates of clients refused as untrusted, kept so that an
                            integrator can move one to trusted/ (the usual OPC UA practice)

The trust list is read again whenever ``trusted/`` changes: trusting a client needs no restart.
"""

from __future__ import annotations

import contextlib
import hashlib
import ipaddress
import logging
import os
import socket
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.cert_gen import (
    dump_private_key_as_pem,
    generate_private_key,
    generate_self_signed_app_certificate,
)
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from ..listener import quiet_logger

log = logging.getLogger("vision_server")
refusals = quiet_logger("vision_server.opcua.refusals")
"""Refusals a stranger can repeat at will (channels, requests over None, sign-ins, untrusted
certificates), for every module of the front-end: logged once per interval, with a count."""

CERTIFICATE_DAYS = 365
"""How long a certificate the server makes for itself is valid; it makes a new one a day
before."""
MAX_REJECTED = 100
"""Rejected certificates kept (the oldest go first): a client that makes a new certificate per
attempt must not fill the disk."""


class PkiError(Exception):
    """The certificate store cannot be made or read (names the file and the cause)."""


class Pki:
    """The folders of one certificate store (see the module)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.own = root / "own"
        self.cert = self.own / "cert.der"
        self.key = self.own / "private" / "key.pem"
        self.trusted = root / "trusted"
        self.rejected = root / "rejected"

    async def ensure(self, application_uri: str, host: str) -> None:
        """Make the folders, and the server's key and certificate where they are missing, or
        the certificate expires within a day or no longer names ``application_uri`` and
        ``host`` (a DNS name, or an IP address entry for an address)."""
        try:
            for folder in (self.own, self.trusted, self.rejected):
                folder.mkdir(parents=True, exist_ok=True)
            self.key.parent.mkdir(mode=0o700, exist_ok=True)
            os.chmod(self.key.parent, 0o700)
            if self.key.is_file():
                key = serialization.load_pem_private_key(self.key.read_bytes(), password=None)
                if not isinstance(key, rsa.RSAPrivateKey):
                    raise ValueError(f"{self.key} is not an RSA key")
            else:
                key = generate_private_key()
                _write_private(self.key, dump_private_key_as_pem(key))
                self.cert.unlink(missing_ok=True)  # made for another key
            if self._current(application_uri, host):
                return
            if self.cert.is_file() and not self._made_here():
                # A plant CA's certificate, put here by hand: never replaced by one of ours.
                raise ValueError(
                    f"{self.cert} is not one cellvision made, and it does not name the "
                    f"application URI {application_uri} and the host {host} (or it expires "
                    "within a day): give the server a certificate that names both "
                    "(opcua: advertised_host sets the host), or remove it to have one made"
                )
            certificate = generate_self_signed_app_certificate(
                key,
                f"cellvision OPC UA server {socket.gethostname()}",
                {"organizationName": "cellvision"},
                [x509.UniformResourceIdentifier(application_uri), _host_name(host)],
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
                days=CERTIFICATE_DAYS,
            )
            self.cert.write_bytes(certificate.public_bytes(Encoding.DER))
            log.info("OPC UA: made the server's certificate %s", self.cert)
        except (OSError, ValueError, TypeError) as exc:
            raise PkiError(f"OPC UA certificate store {self.root}: {exc}") from exc

    def _made_here(self) -> bool:
        """Whether the certificate on file is one :meth:`ensure` made (self-signed, cellvision)."""
        try:
            certificate = x509.load_der_x509_certificate(self.cert.read_bytes())
        except ValueError:
            return True  # not a certificate at all: ours to replace
        organizations = certificate.subject.get_attributes_for_oid(NameOID.ORGANIZATION_NAME)
        return certificate.issuer == certificate.subject and any(
            o.value == "cellvision" for o in organizations
        )

    def _current(self, application_uri: str, host: str) -> bool:
        """Whether the certificate on file may serve on: it names both, for a day more."""
        if not self.cert.is_file():
            return False
        try:
            certificate = x509.load_der_x509_certificate(self.cert.read_bytes())
            names = certificate.extensions.get_extension_for_class(x509.SubjectAlternativeName)
        except (ValueError, x509.ExtensionNotFound):
            return False
        left = certificate.not_valid_after_utc - datetime.now(UTC)
        return (
            left > timedelta(days=1)
            and _host_name(host) in names.value
            and x509.UniformResourceIdentifier(application_uri) in names.value
        )

    def reject(self, certificate: x509.Certificate) -> None:
        """Keep a refused client's certificate in ``rejected/`` (bounded in number)."""
        der = certificate.public_bytes(Encoding.DER)
        name = self.rejected / f"{hashlib.sha1(der).hexdigest()}.der"  # noqa: S324
        with contextlib.suppress(OSError):
            if not name.exists():
                name.write_bytes(der)
            kept = sorted(self.rejected.glob("*.der"), key=lambda p: p.stat().st_mtime)
            for old in kept[: max(0, len(kept) - MAX_REJECTED)]:
                old.unlink()


class TrustList:
    """Lets in client applications whose certificate (or its CA) is in ``trusted/``; refused
    ones are kept in ``rejected/``. With ``trust_all``, any client certificate that is valid
    in time is accepted (for commissioning). Checked when a secure channel opens
    (:meth:`check_channel`) and again at CreateSession (``__call__``, which also checks that
    the certificate names the client's application URI)."""

    def __init__(self, pki: Pki, *, trust_all: bool, policies: frozenset[str]) -> None:
        self.pki = pki
        self.trust_all = trust_all
        self.policies = policies
        """The security policy URIs a channel may use (the None policy's only where allowed)."""
        self._seen: tuple[tuple[str, float], ...] | None = None
        self._exact: set[bytes] = set()
        self._verifier: Any = None
        # Valid in time, naming the client's application URI, a client's certificate: what
        # every certificate must be at CreateSession; whether it is trusted is checked after.
        self._basic = CertificateValidator(
            CertificateValidatorOptions.TIME_RANGE
            | CertificateValidatorOptions.URI
            | CertificateValidatorOptions.PEER_CLIENT
        )

    def _refresh(self) -> None:
        """Read ``trusted/`` again when a file in it changed (a client trusted at run time)."""
        try:
            files = sorted(p for p in self.pki.trusted.iterdir() if p.is_file())
            seen = tuple((p.name, p.stat().st_mtime) for p in files)
        except OSError:
            files, seen = [], ()
        if seen == self._seen:
            return
        certificates: list[x509.Certificate] = []
        for path in files:
            with contextlib.suppress(OSError, ValueError):
                certificates.append(_load_certificate(path.read_bytes()))
        self._exact = {_fingerprint(c) for c in certificates}
        self._verifier = None
        if certificates:  # CAs among them let in the certificates they signed
            with contextlib.suppress(ValueError):
                store = x509.verification.Store(certificates)
                self._verifier = TrustStore([], []).policy_builder.store(store)
        self._seen = seen

    def trusted(self, certificate: x509.Certificate) -> bool:
        if self.trust_all:
            return True
        self._refresh()
        if _fingerprint(certificate) in self._exact:
            return True
        if self._verifier is None:
            return False
        try:
            self._verifier.build_client_verifier().verify(certificate, [])
        except Exception:  # cryptography's VerificationError, or a certificate it cannot use
            return False
        return True

    def check_channel(self, policy: str, der: bytes | None) -> tuple[int, str] | None:
        """Why a secure channel with ``policy`` and the client certificate ``der`` is
        refused (an OPC UA status code and words), or None."""
        if policy not in self.policies:
            return ua.StatusCodes.BadSecurityPolicyRejected, f"the policy {policy} is not offered"
        if policy.endswith("#None"):
            return None
        if not der:
            return ua.StatusCodes.BadCertificateInvalid, "no client certificate"
        try:
            certificate = x509.load_der_x509_certificate(der)
        except ValueError:
            return ua.StatusCodes.BadCertificateInvalid, "the client certificate is not DER X.509"
        now = datetime.now(UTC)
        if not certificate.not_valid_before_utc <= now <= certificate.not_valid_after_utc:
            return (
                ua.StatusCodes.BadCertificateTimeInvalid,
                "the client certificate is not valid now",
            )
        if not self.trusted(certificate):
            self.pki.reject(certificate)
            refusals.info(
                "OPC UA: refused an untrusted client (its certificate is now in %s; move it to "
                "%s to trust it)",
                self.pki.rejected,
                self.pki.trusted,
            )
            return ua.StatusCodes.BadCertificateUntrusted, "the client certificate is not trusted"
        return None

    async def __call__(self, cert: x509.Certificate, app: ua.ApplicationDescription) -> None:
        await self._basic.validate(cert, app)
        if not self.trusted(cert):
            self.pki.reject(cert)
            raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)


def _host_name(host: str) -> x509.GeneralName:
    """``host`` as a certificate names it: an IP address entry for an address, else DNS."""
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def _write_private(path: Path, data: bytes) -> None:
    """Write a private key readable by the server's user only (0600 from its creation)."""
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "wb") as file:
        file.write(data)
    os.chmod(path, 0o600)


def _fingerprint(certificate: x509.Certificate) -> bytes:
    return hashlib.sha256(certificate.public_bytes(Encoding.DER)).digest()


def _load_certificate(data: bytes) -> x509.Certificate:
    """A certificate file's certificate, DER or PEM (ValueError otherwise)."""
    if data.lstrip().startswith(b"-----BEGIN"):
        return x509.load_pem_x509_certificate(data)
    return x509.load_der_x509_certificate(data)


def load_certificate_file(path: Path) -> x509.Certificate:
    """A certificate file (DER or PEM); raises :class:`PkiError` naming it."""
    try:
        return _load_certificate(path.read_bytes())
    except (OSError, ValueError) as exc:
        raise PkiError(f"cannot read the certificate {path}: {exc}") from exc


def same_certificate(a: x509.Certificate, b: x509.Certificate) -> bool:
    return _fingerprint(a) == _fingerprint(b)


__all__ = [
    "MAX_REJECTED",
    "Pki",
    "PkiError",
    "TrustList",
    "load_certificate_file",
    "refusals",
    "same_certificate",
]

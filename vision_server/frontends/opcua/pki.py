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
import logging
import os
import socket
from pathlib import Path

from asyncua import ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID

log = logging.getLogger("vision_server")

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
        """Make the folders, and the server's certificate and key where they are missing
        (or the certificate no longer names ``application_uri`` and ``host``, or expired)."""
        try:
            for folder in (self.own, self.trusted, self.rejected):
                folder.mkdir(parents=True, exist_ok=True)
            self.key.parent.mkdir(mode=0o700, exist_ok=True)
            os.chmod(self.key.parent, 0o700)
            made = not self.key.is_file()
            old_umask = os.umask(0o077)  # the key is written readable by the server's user only
            try:
                await setup_self_signed_certificate(
                    self.key,
                    self.cert,
                    application_uri,
                    host,
                    [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
                    {
                        "commonName": f"cellvision OPC UA server on {socket.gethostname()}",
                        "organizationName": "cellvision",
                    },
                )
            finally:
                os.umask(old_umask)
            if made:
                log.info("OPC UA: made the server's certificate %s", self.cert)
        except (OSError, ValueError) as exc:
            raise PkiError(f"OPC UA certificate store {self.root}: {exc}") from exc

    def thumbprint(self) -> str:
        """The server certificate's SHA-1 thumbprint (what OPC UA tools show), hex."""
        return hashlib.sha1(self.cert.read_bytes()).hexdigest()  # noqa: S324 (a name, not security)

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
    in time and names its application is accepted (for commissioning)."""

    def __init__(self, pki: Pki, *, trust_all: bool) -> None:
        self.pki = pki
        self.trust_all = trust_all
        self._seen: tuple[tuple[str, float], ...] | None = None
        self._exact: set[bytes] = set()
        self._store: TrustStore | None = None
        # Valid in time, naming the client's application URI, a client's certificate: what
        # every certificate must be; whether it is trusted is checked after (see __call__).
        self._basic = CertificateValidator(
            CertificateValidatorOptions.TIME_RANGE
            | CertificateValidatorOptions.URI
            | CertificateValidatorOptions.PEER_CLIENT
        )

    async def _refresh(self) -> None:
        """Read ``trusted/`` again when a file in it changed (a client trusted at run time)."""
        try:
            files = sorted(p for p in self.pki.trusted.iterdir() if p.is_file())
            seen = tuple((p.name, p.stat().st_mtime) for p in files)
        except OSError:
            files, seen = [], ()
        if seen == self._seen:
            return
        exact: set[bytes] = set()
        for path in files:
            with contextlib.suppress(OSError, ValueError):
                exact.add(_fingerprint(_load_certificate(path.read_bytes())))
        store: TrustStore | None = None
        if exact:  # CAs among them let in the certificates they signed
            store = TrustStore([self.pki.trusted], [])
            try:
                await store.load()
            except Exception as exc:  # a bad file in trusted/ must not stop every client
                log.warning("OPC UA: cannot read the trust list %s: %s", self.pki.trusted, exc)
                store = None
        self._exact, self._store, self._seen = exact, store, seen

    async def __call__(self, cert: x509.Certificate, app: ua.ApplicationDescription) -> None:
        await self._basic.validate(cert, app)
        if self.trust_all:
            return
        await self._refresh()
        if _fingerprint(cert) in self._exact:
            return
        if self._store is not None and self._store.validate(cert):
            return
        self.pki.reject(cert)
        log.info(
            "OPC UA: refused the untrusted client %r (its certificate is now in %s; move it to "
            "%s to trust it)",
            app.ApplicationUri,
            self.pki.rejected,
            self.pki.trusted,
        )
        raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)


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
    "same_certificate",
]

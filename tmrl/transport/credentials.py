"""Credentials: the relay's TLS key and certificate, and the trainer's signing key.

``key.pem`` (the private key) stays on the server machine. ``certificate.pem`` is public: copy it,
and only it, to every worker and trainer machine. The file names are tlspyo's.

``trainer_signing_key.pem`` (Ed25519, made by the trainer when it first starts) stays on the
trainer machine: the trainer signs every weights broadcast with it and proves to the relay that it
is the trainer. ``trainer_public_key.pem`` is public: a worker or relay that finds it in its
credentials folder accepts weights (and a trainer) signed by that key only.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
from pathlib import Path
from typing import Any

from tmrl.util import atomic_write_bytes

__all__ = [
    "CERT_FILE",
    "DEFAULT_HOSTNAME",
    "KEY_FILE",
    "TRAINER_KEY_FILE",
    "TRAINER_PUBLIC_KEY_FILE",
    "TrainerKey",
    "ensure_credentials",
    "ensure_trainer_key",
    "load_trainer_public_key",
    "verify_signature",
]

KEY_FILE = "key.pem"
CERT_FILE = "certificate.pem"
#: The name the certificate is issued for; links check it (their ``hostname`` argument), so the
#: server's IP address does not need to be in the certificate.
DEFAULT_HOSTNAME = "default"
TRAINER_KEY_FILE = "trainer_signing_key.pem"
TRAINER_PUBLIC_KEY_FILE = "trainer_public_key.pem"
#: Prefix of the relay's challenge that a trainer signs (never a valid weights header).
HANDSHAKE_CONTEXT = b"tmrl trainer handshake\0"


def ensure_credentials(
    directory: str | os.PathLike[str], hostname: str = DEFAULT_HOSTNAME
) -> tuple[Path, Path]:
    """Create a TLS private key and a self-signed certificate in ``directory``, keeping existing ones.

    - both files present: nothing is written;
    - only ``certificate.pem`` present (a worker or trainer machine): kept as it is, no key is made;
    - only ``key.pem`` present: a new certificate is issued for that key;
    - neither: a new RSA 3072 key and a 10-year certificate for ``hostname`` (plus ``localhost`` and
      ``127.0.0.1``) are written.

    Files are written atomically; the key file is readable by its owner only (mode 0600).

    Args:
        directory: the credentials folder (created when missing).
        hostname: the name put in the certificate; links must use the same ``hostname``.

    Returns:
        ``(key_path, certificate_path)``; the key path may not exist on a machine that only holds
        the certificate.
    """
    folder = Path(directory)
    key_path, cert_path = folder / KEY_FILE, folder / CERT_FILE
    if cert_path.exists():
        return key_path, cert_path
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import rsa
    from cryptography.x509.oid import NameOID

    folder.mkdir(parents=True, exist_ok=True)
    key: Any
    if key_path.exists():
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    else:
        key = rsa.generate_private_key(public_exponent=65537, key_size=3072)
        pem = key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
        atomic_write_bytes(key_path, pem, mode=0o600)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, hostname)])
    now = datetime.datetime.now(datetime.timezone.utc)
    sans: list[x509.GeneralName] = [x509.DNSName(hostname), x509.DNSName("localhost")]
    sans.append(x509.IPAddress(ipaddress.ip_address("127.0.0.1")))
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(days=1))
        .not_valid_after(now + datetime.timedelta(days=3650))
        .add_extension(x509.SubjectAlternativeName(sans), critical=False)
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    atomic_write_bytes(cert_path, cert.public_bytes(serialization.Encoding.PEM))
    os.chmod(cert_path, 0o644)
    return key_path, cert_path


class TrainerKey:
    """The trainer's Ed25519 signing key (see :func:`ensure_trainer_key`).

    Args:
        private_pem: the private key, PEM (PKCS8, unencrypted).

    Attributes:
        public_pem: the public key, PEM (SubjectPublicKeyInfo): what workers and relays pin.
    """

    def __init__(self, private_pem: bytes):
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

        key = serialization.load_pem_private_key(private_pem, password=None)
        if not isinstance(key, Ed25519PrivateKey):
            raise ValueError("not an Ed25519 private key")
        self._key = key
        self.private_pem = private_pem
        self.public_pem = key.public_key().public_bytes(
            serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
        )

    def sign(self, message: bytes) -> bytes:
        """The 64-byte Ed25519 signature of ``message``."""
        return self._key.sign(message)


def ensure_trainer_key(directory: str | os.PathLike[str]) -> TrainerKey:
    """The trainer's signing key from ``directory``, created there when missing.

    Writes ``trainer_signing_key.pem`` (mode 0600) and ``trainer_public_key.pem`` atomically;
    existing files are kept.

    Raises:
        UserError: the key file exists but is not an Ed25519 private key.
    """
    from tmrl.errors import UserError

    folder = Path(directory)
    path = folder / TRAINER_KEY_FILE
    if path.exists():
        try:
            key = TrainerKey(path.read_bytes())
        except (ValueError, TypeError) as err:
            raise UserError(
                f"{path} is not an Ed25519 private key ({err}): delete it to let the trainer make a new one "
                f"(then copy the new {TRAINER_PUBLIC_KEY_FILE} to the workers)"
            ) from None
    else:
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

        pem = Ed25519PrivateKey.generate().private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, pem, mode=0o600)
        key = TrainerKey(pem)
    public = folder / TRAINER_PUBLIC_KEY_FILE
    if not public.exists():
        atomic_write_bytes(public, key.public_pem)
    return key


def load_trainer_public_key(directory: str | os.PathLike[str] | None) -> bytes | None:
    """The pinned ``trainer_public_key.pem`` of ``directory`` (its PEM bytes), or ``None`` when
    there is none.

    Raises:
        UserError: the file exists but is not an Ed25519 public key.
    """
    from tmrl.errors import UserError

    if directory is None:
        return None
    path = Path(directory) / TRAINER_PUBLIC_KEY_FILE
    try:
        pem = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as err:
        raise UserError(f"cannot read {path} ({err}): fix its permissions or delete it") from None
    try:
        _public_key(pem)
    except ValueError as err:
        raise UserError(
            f"{path} is not an Ed25519 public key ({err}): copy trainer_public_key.pem again from the "
            "trainer's credentials folder"
        ) from None
    return pem


def _public_key(pem: bytes) -> Any:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    key = serialization.load_pem_public_key(pem)
    if not isinstance(key, Ed25519PublicKey):
        raise ValueError("not an Ed25519 public key")
    return key


def verify_signature(public_pem: bytes, signature: bytes, message: bytes) -> bool:
    """Whether ``signature`` is ``message`` signed by the key ``public_pem`` (never raises)."""
    from cryptography.exceptions import InvalidSignature

    try:
        _public_key(public_pem).verify(signature, message)
        return True
    except (InvalidSignature, ValueError, TypeError):
        return False

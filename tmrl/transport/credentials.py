"""TLS credentials for the relay: a private key and a self-signed certificate.

``key.pem`` (the private key) stays on the server machine. ``certificate.pem`` is public: copy it,
and only it, to every worker and trainer machine. The file names are tlspyo's.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
from pathlib import Path
from typing import Any

from tmrl.util import atomic_write_bytes

__all__ = ["CERT_FILE", "DEFAULT_HOSTNAME", "KEY_FILE", "ensure_credentials"]

KEY_FILE = "key.pem"
CERT_FILE = "certificate.pem"
#: The name the certificate is issued for; links check it (their ``hostname`` argument), so the
#: server's IP address does not need to be in the certificate.
DEFAULT_HOSTNAME = "default"


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

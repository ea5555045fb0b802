"""A certificate authority and the certificates of a relaxmap deployment, for zenoh's TLS links."""

from __future__ import annotations

import datetime
import ipaddress
from collections.abc import Sequence
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

ROUTER_NAME = "router"  # common name of the routers' certificate (trusted to forward map updates)
DEFAULT_DAYS = 365


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()))
    path.chmod(0o600)


def _write_cert(path: Path, cert: x509.Certificate) -> None:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _san(hosts: list[str]) -> x509.SubjectAlternativeName:
    names: list[x509.GeneralName] = []
    for h in dict.fromkeys(hosts):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    return x509.SubjectAlternativeName(names)


def _issue(common_name: str, key: ec.EllipticCurvePrivateKey, ca_cert: x509.Certificate,
           ca_key: ec.EllipticCurvePrivateKey, *, hosts: list[str], days: int) -> x509.Certificate:
    now = datetime.datetime.now(datetime.timezone.utc)
    return (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
            .issuer_name(ca_cert.subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
            .add_extension(_san(hosts), critical=False)
            .sign(ca_key, hashes.SHA256()))


def _new_ca(out: Path, *, days: int) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    key = _key()
    now = datetime.datetime.now(datetime.timezone.utc)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "relaxmap CA")])
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .sign(key, hashes.SHA256()))
    _write_cert(out / "ca.pem", cert)
    _write_key(out / "ca-key.pem", key)
    return cert, key


def _load_ca(out: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    cert = x509.load_pem_x509_certificate((out / "ca.pem").read_bytes())
    key = serialization.load_pem_private_key((out / "ca-key.pem").read_bytes(), password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise ValueError(f"{out / 'ca-key.pem'}: not an EC key written by relaxmap certs")
    return cert, key


def write_certs(out: str | Path, names: Sequence[str], *, router_hosts: Sequence[str] = (),
                days: int = DEFAULT_DAYS) -> dict[str, Path]:
    """Write a CA (or reuse the one in ``out``) and one folder per identity, ready to copy to a host.

    ``out/ca.pem`` + ``out/ca-key.pem`` is the authority (the key stays where it was made). For
    ``router`` and each of ``names``, ``out/<name>/`` holds ``ca.pem``, ``cert.pem`` and ``key.pem``:
    the certificate's common name is the identity the routers' access control sees. The routers'
    certificate also names ``router_hosts`` (addresses or DNS names clients connect to), plus
    127.0.0.1 and localhost.

    Returns the folder of each identity.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    bad = [n for n in names if not n or "/" in n or n in (".", "..") or n == ROUTER_NAME]
    if bad:
        raise ValueError(f"identity names must be non-empty, without '/', and not {ROUTER_NAME!r} "
                         f"(always written): {bad}")
    ca_cert, ca_key = _load_ca(out) if (out / "ca.pem").is_file() else _new_ca(out, days=days)
    folders = {}
    for name in (ROUTER_NAME, *names):
        folder = out / name
        folder.mkdir(exist_ok=True)
        key = _key()
        hosts = [*router_hosts, "127.0.0.1", "localhost"] if name == ROUTER_NAME else [name]
        _write_key(folder / "key.pem", key)
        _write_cert(folder / "cert.pem", _issue(name, key, ca_cert, ca_key, hosts=hosts, days=days))
        _write_cert(folder / "ca.pem", ca_cert)
        folders[name] = folder
    return folders

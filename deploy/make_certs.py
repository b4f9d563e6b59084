#!/usr/bin/env python3
"""Make a development certificate authority and one TLS certificate per role of a pd-service
deployment, for Zenoh's TLS with mutual authentication (deploy/README.md, "TLS").

    pip install 'pd-service[deploy]'            # the cryptography package
    python deploy/make_certs.py deploy/certs    # ca.pem + <role>.pem / <role>-key.pem
    python deploy/make_certs.py OUT --role robot-7 --host router.example.org

Every certificate's subject common name (CN) is its role's name: the routers' access control
matches clients by it (``cert_common_names``, written by deploy/make_acl.py from a sessions
file with a ``[tls]`` table), so a role's key IS its identity: keep each key on its host,
readable by its service account only. The routers' certificates (router-a, router-b by
default) name the hosts clients reach them by (``--host``; router-a, router-b, localhost and
127.0.0.1 by default) and serve as client certificates too, for the mesh link between them.

FOR DEVELOPMENT AND TESTS: the CA key is written beside the certificates, unencrypted.
A real deployment keeps its CA offline (or uses the organisation's PKI) and issues each host
its certificate; only ``ca.pem`` and the host's own pair go on a host. Exit status 2 with a
message when the output cannot be written or an argument is bad.
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

#: The deployment's roles (deploy/zenoh/<role>.json5), each a client certificate.
CLIENT_ROLES = ("service", "link", "admin", "operator", "robot", "display")
#: The routers of compose.yml, each a server and client certificate.
ROUTER_ROLES = ("router-a", "router-b")
#: Hosts a router certificate names (subject alternative names) unless --host is given.
DEFAULT_HOSTS = ("router-a", "router-b", "localhost", "127.0.0.1", "::1")
_ROLE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # make_acl.py's user-name rule


def _crypto() -> Any:
    try:
        from cryptography import x509
    except ImportError:
        raise SystemExit("make_certs.py: needs the cryptography package: "
                         "pip install 'pd-service[deploy]'") from None
    return x509


def _name(cn: str) -> Any:
    x509 = _crypto()
    from cryptography.x509.oid import NameOID

    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "pd-service development"),
                      x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _key() -> Any:
    from cryptography.hazmat.primitives.asymmetric import ec

    return ec.generate_private_key(ec.SECP256R1())


def _san(hosts: Sequence[str]) -> Any:
    x509 = _crypto()
    names: list[Any] = []
    for h in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    return x509.SubjectAlternativeName(names)


def make_ca(days: int) -> tuple[Any, Any]:
    """A self-signed CA certificate (CN "pd-service development CA") and its key."""
    x509 = _crypto()
    from cryptography.hazmat.primitives import hashes

    key = _key()
    now = dt.datetime.now(dt.UTC)
    cert = (x509.CertificateBuilder().subject_name(_name("pd-service development CA"))
            .issuer_name(_name("pd-service development CA")).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True,
                                         crl_sign=True, content_commitment=False,
                                         key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, encipher_only=False,
                                         decipher_only=False), critical=True)
            .sign(key, hashes.SHA256()))
    return cert, key


def make_leaf(ca: tuple[Any, Any], cn: str, hosts: Sequence[str], server: bool,
              days: int) -> tuple[Any, Any]:
    """A certificate of CN ``cn`` signed by ``ca`` (cert, key): a client certificate, and
    with ``server`` also a server one naming ``hosts``."""
    x509 = _crypto()
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID

    ca_cert, ca_key = ca
    key = _key()
    now = dt.datetime.now(dt.UTC)
    usages = [ExtendedKeyUsageOID.CLIENT_AUTH]
    if server:
        usages.append(ExtendedKeyUsageOID.SERVER_AUTH)
    builder = (x509.CertificateBuilder().subject_name(_name(cn))
               .issuer_name(ca_cert.subject).public_key(key.public_key())
               .serial_number(x509.random_serial_number())
               .not_valid_before(now - dt.timedelta(minutes=5))
               .not_valid_after(now + dt.timedelta(days=days))
               .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
               .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
               # rustls wants a subject alternative name even on a client certificate
               .add_extension(_san(hosts if server else [cn]), critical=False))
    return builder.sign(ca_key, hashes.SHA256()), key


def _pem(obj: Any) -> bytes:
    from cryptography.hazmat.primitives import serialization

    if hasattr(obj, "private_bytes"):
        return bytes(obj.private_bytes(serialization.Encoding.PEM,
                                       serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()))
    return bytes(obj.public_bytes(serialization.Encoding.PEM))


def write_all(out: Path, clients: Sequence[str], routers: Sequence[str], hosts: Sequence[str],
              days: int) -> list[Path]:
    """Write ``ca.pem``, ``ca-key.pem`` and ``<role>.pem`` / ``<role>-key.pem`` for every
    role into ``out`` (keys readable by their owner only); the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    ca = make_ca(days)
    written = [_write(out / "ca.pem", _pem(ca[0]), 0o644),
               _write(out / "ca-key.pem", _pem(ca[1]), 0o600)]
    for role in [*routers, *clients]:
        cert, key = make_leaf(ca, role, hosts, role in routers, days)
        written += [_write(out / f"{role}.pem", _pem(cert), 0o644),
                    _write(out / f"{role}-key.pem", _pem(key), 0o600)]
    return written


def _write(path: Path, data: bytes, mode: int) -> Path:
    path.write_bytes(data)
    path.chmod(mode)
    return path


def _role(value: str) -> str:
    if not _ROLE.fullmatch(value):
        raise argparse.ArgumentTypeError(f"a role name ({_ROLE.pattern}), got {value!r}")
    return value


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="make_certs.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="directory to write the PEM files into")
    ap.add_argument("--role", action="append", type=_role, metavar="NAME",
                    help="a client role (repeatable; default: "
                         f"{', '.join(CLIENT_ROLES)})")
    ap.add_argument("--router", action="append", type=_role, metavar="NAME",
                    help=f"a router (repeatable; default: {', '.join(ROUTER_ROLES)})")
    ap.add_argument("--host", action="append", metavar="NAME",
                    help="a host name or address the routers are reached by (repeatable; "
                         f"default: {', '.join(DEFAULT_HOSTS)})")
    ap.add_argument("--days", type=int, default=365,
                    help="validity of every certificate, days (default 365)")
    args = ap.parse_args(argv)
    if args.days < 1:
        ap.error("--days must be at least 1")
    try:
        written = write_all(args.out, args.role or CLIENT_ROLES, args.router or ROUTER_ROLES,
                            args.host or DEFAULT_HOSTS, args.days)
    except OSError as exc:
        print(f"make_certs.py: {exc}", file=sys.stderr)
        return 2
    for p in written:
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Make a small PKI for a feedmon cell: a CA, the router's certificate and one client
certificate per role, with the ``openssl`` command line tool (no Python packages needed).

Usage::

    python deploy/tls/make_certs.py OUT_DIR [--router-san DNS:feedmon-router,IP:10.1.2.3]
                                            [--clients monitor,controller,viewer] [--days 825]

Writes into OUT_DIR (PEM files, keys mode 0600):

* ``ca.pem`` / ``ca-key.pem`` — the cell CA. Keep ``ca-key.pem`` offline; only
  ``ca.pem`` is distributed (every node needs it as ``root_ca_certificate``).
* ``router.pem`` / ``router-key.pem`` — CN ``router``; subjectAltName
  ``DNS:feedmon-router, DNS:localhost, IP:127.0.0.1`` plus ``--router-san``.
  Clients check that the host in their ``connect`` endpoint is one of these names
  (``verify_name_on_connect``), so add the router's real name or address.
* ``<role>.pem`` / ``<role>-key.pem`` per client — CN = role. The router's access
  control matches subjects on this common name (``cert_common_names``).

Keys are ECDSA P-256 (PKCS#8). Existing files are never overwritten (the CA is kept,
so new client certificates can be issued later with ``--clients NAME``).
Also importable: :func:`make_ca` and :func:`make_cert` are used by the tests.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

DEFAULT_ROUTER_SAN = ("DNS:feedmon-router", "DNS:localhost", "IP:127.0.0.1")
DEFAULT_CLIENTS = ("monitor", "controller", "viewer")


def _openssl(*args: str) -> None:
    exe = shutil.which("openssl")
    if exe is None:
        raise OSError("the 'openssl' command is needed to make certificates but was not found on PATH")
    proc = subprocess.run([exe, *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise OSError(f"openssl {args[0]} failed: {proc.stderr.strip()}")


def _key(path: Path) -> None:
    _openssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", str(path))
    os.chmod(path, 0o600)


def make_ca(out: str | os.PathLike, name: str = "ca", cn: str = "feedmon cell CA", days: int = 3650) -> tuple[Path, Path]:
    """Self-signed CA ``<name>.pem`` + ``<name>-key.pem`` in ``out``; returns (cert, key)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cert, key = out / f"{name}.pem", out / f"{name}-key.pem"
    if cert.exists() and key.exists():
        return cert, key
    _key(key)
    _openssl(
        "req", "-x509", "-new", "-key", str(key), "-out", str(cert), "-days", str(days), "-sha256",
        "-subj", f"/CN={cn}",
        "-addext", "basicConstraints=critical,CA:TRUE,pathlen:0",
        "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        "-addext", "subjectKeyIdentifier=hash",
    )
    return cert, key


def make_cert(
    out: str | os.PathLike,
    name: str,
    ca: tuple[Path, Path],
    *,
    cn: str | None = None,
    san: tuple[str, ...] = (),
    server: bool = False,
    days: int = 825,
) -> tuple[Path, Path]:
    """Certificate ``<name>.pem`` + ``<name>-key.pem`` signed by ``ca`` (cert, key); CN defaults to ``name``.

    ``server=True``: usable as TLS server *and* client (a router also connects to other
    routers); otherwise a client certificate. ``san`` e.g. ``("DNS:host", "IP:10.0.0.5")``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cert, key = out / f"{name}.pem", out / f"{name}-key.pem"
    if cert.exists() and key.exists():
        return cert, key
    _key(key)
    ext = [
        "basicConstraints=critical,CA:FALSE",
        "keyUsage=critical,digitalSignature",
        "extendedKeyUsage=" + ("serverAuth,clientAuth" if server else "clientAuth"),
        "subjectKeyIdentifier=hash",
        "authorityKeyIdentifier=keyid",
    ]
    if san:
        ext.append("subjectAltName=" + ",".join(san))
    with tempfile.TemporaryDirectory() as tmp:
        csr, extfile = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
        extfile.write_text("\n".join(ext) + "\n")
        _openssl("req", "-new", "-key", str(key), "-out", str(csr), "-subj", f"/CN={cn or name}")
        _openssl(
            "x509", "-req", "-in", str(csr), "-CA", str(ca[0]), "-CAkey", str(ca[1]), "-CAcreateserial",
            "-CAserial", str(Path(tmp) / "ca.srl"), "-out", str(cert), "-days", str(days), "-sha256",
            "-extfile", str(extfile),
        )
    return cert, key


def make_cell(out, *, router_san=(), clients=DEFAULT_CLIENTS, days: int = 825) -> dict[str, tuple[Path, Path]]:
    """CA, router and client certificates for one cell (see the module docstring)."""
    ca = make_ca(out)
    made = {"ca": ca}
    made["router"] = make_cert(out, "router", ca, san=tuple(dict.fromkeys((*DEFAULT_ROUTER_SAN, *router_san))),
                               server=True, days=days)
    for role in clients:
        made[role] = make_cert(out, role, ca, days=days)
    return made


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", help="output directory")
    p.add_argument("--router-san", default="", help="extra subjectAltNames of the router, e.g. DNS:cell7-router,IP:10.1.2.3")
    p.add_argument("--clients", default=",".join(DEFAULT_CLIENTS), help="client roles (certificate CNs), comma-separated")
    p.add_argument("--days", type=int, default=825, help="validity of router and client certificates (days)")
    a = p.parse_args(argv)
    san = tuple(s.strip() for s in a.router_san.split(",") if s.strip())
    roles = tuple(s.strip() for s in a.clients.split(",") if s.strip())
    try:
        made = make_cell(a.out, router_san=san, clients=roles, days=a.days)
    except OSError as exc:
        print(f"make_certs: error: {exc}", file=sys.stderr)
        return 2
    for name, (cert, key) in made.items():
        print(f"{name:<12} {cert}  {key}")
    print("keep ca-key.pem offline; give each node ca.pem plus its own certificate and key")
    return 0


if __name__ == "__main__":
    sys.exit(main())

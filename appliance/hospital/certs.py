"""A hospital CA and the nodes' certificates, made with ``openssl`` into the description's ``[tls]`` folder.

For a trial, or a hospital without a PKI of its own: the CA is made once and kept, and each node lacking a
certificate gets a key and a certificate signed by it, naming the node's host in subjectAltName (an IP address
or a DNS name: clients and the other nodes check it against the address they reach the node at) and usable by
both ends of a route. A hospital whose own CA signs the nodes' certificates puts them, and that CA's
certificate as ``ca.crt``, in the folder instead. Keys are mode 0600.
"""

from __future__ import annotations

import ipaddress
import re
import shutil
import subprocess
from pathlib import Path

from appliance.errors import ConfigError
from appliance.hospital.description import Hospital, Node
from appliance.hospital.tls import TlsFolder

CA_DAYS = 3650
NODE_DAYS = 825
"""How long a node's certificate is valid: the longest that common TLS clients still accept from a CA."""
KEY_OPTIONS = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-noenc"]
DNS_NAME = re.compile(r"[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?")


def make_certificates(hospital: Hospital) -> list[Path]:
    """Make what the ``[tls]`` folder lacks: the CA (its certificate and key), then each node's key and certificate.
    The files made, in that order."""
    if hospital.tls is None:
        raise ConfigError('the hospital description has no [tls] table: add one with dir = "FOLDER" for the CA and '
                          'the nodes\' certificates')
    tls = hospital.tls
    tls.path.mkdir(mode=0o755, parents=True, exist_ok=True)
    made = []
    if not tls.ca_file.exists():
        _openssl(["req", "-x509", *KEY_OPTIONS, "-keyout", str(tls.ca_key), "-out", str(tls.ca_file),
                  "-days", str(CA_DAYS), "-subj", f"/CN={_escaped(hospital.cluster)} hospital engine CA",
                  "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign"],
                 tls.ca_key)
        made += [tls.ca_file, tls.ca_key]
    for node in hospital.nodes:
        if not tls.cert_file(node.name).exists():
            made += _node_certificate(tls, node)
    return made


def subject_alt_name(host: str) -> str:
    """The subjectAltName naming ``host``: ``IP:`` for an address, ``DNS:`` for a host name."""
    try:
        return f"IP:{ipaddress.ip_address(host)}"
    except ValueError:
        if not DNS_NAME.fullmatch(host):
            raise ConfigError(f"node host {host!r}: neither an IP address nor a DNS name, so no certificate can "
                              f"name it") from None
        return f"DNS:{host}"


def _node_certificate(tls: TlsFolder, node: Node) -> list[Path]:
    if not tls.ca_key.exists():
        raise ConfigError(f"[tls] {tls.cert_file(node.name)} does not exist, and this folder has no key for "
                          f"{tls.ca_file.name}: the hospital's CA must sign node {node.name}'s certificate")
    cert, key = tls.cert_file(node.name), tls.key_file(node.name)
    _openssl(["req", "-x509", *KEY_OPTIONS, "-keyout", str(key), "-out", str(cert), "-days", str(NODE_DAYS),
              "-CA", str(tls.ca_file), "-CAkey", str(tls.ca_key), "-subj", f"/CN={_escaped(node.name)}",
              "-addext", f"subjectAltName={subject_alt_name(node.host)}",
              "-addext", "basicConstraints=critical,CA:FALSE", "-addext", "keyUsage=critical,digitalSignature",
              "-addext", "extendedKeyUsage=serverAuth,clientAuth"], key)
    return [cert, key]


def _openssl(arguments: list[str], key: Path) -> None:
    """Run openssl, then make sure ``key``, the private key it wrote, is readable by its owner alone."""
    binary = shutil.which("openssl")
    if binary is None:
        raise ConfigError("openssl is not installed (Debian: apt-get install openssl): it makes the certificates")
    result = subprocess.run([binary, *arguments], check=False, capture_output=True, text=True, timeout=60)
    if key.exists():
        key.chmod(0o600)
    if result.returncode != 0:
        raise ConfigError(f"openssl {arguments[0]} failed: {result.stderr.strip()}")


def _escaped(name: str) -> str:
    """``name`` as a value in openssl's ``-subj``, where '/', '=' and '+' separate the parts."""
    return re.sub(r"([/=+\\])", r"\\\1", name)

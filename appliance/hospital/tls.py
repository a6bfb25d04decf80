"""The engine's TLS files, found by name in one folder, and the SSL context every client of the engine uses.

The folder holds ``ca.crt``, the hospital CA that every node and client trusts, and ``<node>.crt`` and
``<node>.key`` for each node: its certificate, signed by that CA and naming the node's host, and its key. One
folder named once in the description, rather than a path per file, because ward IT then adds a node by dropping
two files named after it, and ``appliance hospital certs`` writes exactly this layout.
"""

from __future__ import annotations

import ssl
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from appliance.errors import ConfigError

CA_CERT = "ca.crt"
CA_KEY = "ca.key"
"""The throw-away CA's key, made beside its certificate by ``appliance hospital certs``; no node or client reads
it, and a hospital whose own CA signs the nodes' certificates has none here."""
HANDSHAKE_TIMEOUT_S = 5
"""How long a node waits for a TLS handshake: the server's half a second is short for a busy small server."""


@dataclass(frozen=True)
class TlsFolder:
    """The folder of the hospital CA's certificate and each node's certificate and key."""

    path: Path

    @property
    def ca_file(self) -> Path:
        return self.path / CA_CERT

    @property
    def ca_key(self) -> Path:
        return self.path / CA_KEY

    def cert_file(self, node: str) -> Path:
        return self.path / f"{node}.crt"

    def key_file(self, node: str) -> Path:
        return self.path / f"{node}.key"

    def node_files(self, node: str) -> tuple[Path, Path, Path]:
        """The CA's certificate and ``node``'s certificate and key, or a ConfigError naming the first missing."""
        files = (self.ca_file, self.cert_file(node), self.key_file(node))
        for path in files:
            if not path.is_file():
                raise ConfigError(f"[tls] {path} does not exist: the folder {self.path} needs {CA_CERT} and "
                                  f"{node}.crt and {node}.key for node {node} (`appliance hospital certs` makes them)")
        return files


def client_context(ca_file: Path) -> ssl.SSLContext:
    """A client's context: it trusts the hospital CA alone and checks that a node's certificate names the address it
    was reached at."""
    try:
        return ssl.create_default_context(cafile=str(ca_file))
    except (OSError, ssl.SSLError) as exc:
        raise ConfigError(f"the hospital CA {ca_file}: not a readable certificate ({exc})") from None


def tls_urls(urls: Sequence[str]) -> list[str]:
    """``urls`` with the scheme ``tls://``: the client then speaks TLS before anything else it says to a node."""
    return [f"tls://{url.partition('://')[2] or url}" for url in urls]

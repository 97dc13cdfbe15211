"""Where a secure bus's credentials live and how a session uses them.

``neso secure init [DIR]`` (``cli/secure.py``) writes into DIR (default :func:`default_dir`):

- ``ca.pem`` — the bus's certificate authority (public: copy it to every machine);
- ``ca-key.pem`` — its private key (0600; stays where certificates are issued, never copied);
- ``<identity>.pem`` and ``<identity>-key.pem`` (0600) per identity: every role of the graph
  under its certificate name, plus ``operator`` (dashboard, CLI) and ``replay``;
- ``router.json5`` — a complete Zenoh router config (TLS with mTLS and the ACL) for a
  ``zenohd`` hub on this machine, and ``compose/router.json5``, the same with the paths
  under ``/secure`` for the ``docker-compose.yml`` hub.

A secure session speaks only ``tls/`` endpoints with mutual TLS: it presents
``<identity>.pem``, accepts only peers whose certificate ``ca.pem`` signed (an expired one is
refused), and runs the ACL of :mod:`runtime.acl` on what it receives. Host names are not
checked against the certificate (``verify_name_on_connect`` off): the identity is the
certificate's common name, which the ACL checks, and only this CA signs them.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass

ENV_DIR = "NESO_SECURE_DIR"
CA_FILE = "ca.pem"
CA_KEY_FILE = "ca-key.pem"
ROUTER_FILE = "router.json5"
COMPOSE_DIR = "compose"
CONTAINER_DIR = "/secure"  # where docker-compose.yml mounts DIR


class SecureSetupError(RuntimeError):
    """Credentials missing or unreadable; the text says what to run."""


def default_dir() -> str:
    """``$NESO_SECURE_DIR``, else ``$XDG_CONFIG_HOME/neso/secure`` (``~/.config/neso/secure``):
    per user, outside the checkout, so no key is ever committed."""
    if os.environ.get(ENV_DIR):
        return os.environ[ENV_DIR]
    base = os.environ.get("XDG_CONFIG_HOME") or os.path.join(os.path.expanduser("~"), ".config")
    return os.path.join(base, "neso", "secure")


def cert_file(identity: str) -> str:
    return f"{identity}.pem"


def key_file(identity: str) -> str:
    return f"{identity}-key.pem"


@dataclass(frozen=True)
class Credentials:
    """One identity's files in ``directory`` (see the module docstring)."""

    directory: str
    identity: str

    @property
    def ca(self) -> str:
        return os.path.join(self.directory, CA_FILE)

    @property
    def cert(self) -> str:
        return os.path.join(self.directory, cert_file(self.identity))

    @property
    def key(self) -> str:
        return os.path.join(self.directory, key_file(self.identity))

    def check(self) -> "Credentials":
        """Self, if the three files are there and readable; else :class:`SecureSetupError`."""
        missing = [p for p in (self.ca, self.cert, self.key) if not os.access(p, os.R_OK)]
        if missing:
            raise SecureSetupError(f"no credentials for {self.identity!r} in {self.directory} (missing "
                                   f"{', '.join(os.path.basename(p) for p in missing)}): run `neso secure init` "
                                   f"there, or copy them from the machine that did "
                                   f"(docs/secure-bus.md: a second machine)")
        return self

    def tls(self) -> dict:
        """The ``transport/link/tls`` section: mutual TLS as this identity, this CA only."""
        return {
            "root_ca_certificate": self.ca,
            "listen_certificate": self.cert,
            "listen_private_key": self.key,
            "connect_certificate": self.cert,
            "connect_private_key": self.key,
            "enable_mtls": True,
            "verify_name_on_connect": False,
            "close_link_on_expiration": True,
        }


def router_config(credentials: Credentials, listen: tuple[str, ...]) -> dict:
    """A whole Zenoh config for a router hub (``zenohd -c``): TLS, mTLS, the graph's ACL."""
    from runtime.acl import access_control

    return {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": credentials.tls()}},
        "access_control": access_control(),
    }


def write_router_configs(directory: str, listen: tuple[str, ...] = ("tls/0.0.0.0:7447",)) -> list[str]:
    """``router.json5`` (paths in ``directory``) and ``compose/router.json5`` (paths in the
    container's ``/secure``) for the ``hub`` identity; the paths written."""
    written = []
    for root, path in ((os.path.abspath(directory), os.path.join(directory, ROUTER_FILE)),
                       (CONTAINER_DIR, os.path.join(directory, COMPOSE_DIR, ROUTER_FILE))):
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as f:
            f.write("// written by `neso secure init` from runtime/graph.py: do not edit, run it again\n")
            json.dump(router_config(Credentials(root, "hub"), listen), f, indent=2)
            f.write("\n")
        written.append(path)
    return written

"""``neso secure init [DIR]``: a local CA, one certificate per identity and the router config;
``neso secure acl``: the access-control list the graph makes (what every secure session runs)."""
from __future__ import annotations

import json
import os
import socket


def add_parser(subparsers) -> None:
    from runtime.pki import DEFAULT_DAYS
    from runtime.secure import default_dir

    p = subparsers.add_parser("secure", help="credentials and access control for a secure bus (--secure)")
    sub = p.add_subparsers(dest="secure_command", required=True)
    init = sub.add_parser("init", help="create a CA, a certificate per identity and the router config")
    init.add_argument("dir", nargs="?", default=None, help=f"where (default $NESO_SECURE_DIR or {default_dir()})")
    init.add_argument("--force", action="store_true", help="replace the CA and every certificate already there")
    init.add_argument("--host", action="append", default=None,
                      help="a name or address the certificates name (repeatable; default localhost, 127.0.0.1 and "
                           "this machine's host name)")
    init.add_argument("--days", type=float, default=DEFAULT_DAYS, help=f"validity (default {DEFAULT_DAYS})")
    sub.add_parser("acl", help="print the access-control list generated from the service graph (JSON)")


def run(args) -> int:
    if args.secure_command == "acl":
        from runtime.acl import access_control

        print(json.dumps(access_control(), indent=2))
        return 0
    return init(args)


def init(args) -> int:
    from runtime.graph import identities
    from runtime.pki import issue, make_ca, write_private, write_public
    from runtime.secure import CA_FILE, CA_KEY_FILE, cert_file, default_dir, key_file, write_router_configs

    directory = args.dir or default_dir()
    if os.path.exists(os.path.join(directory, CA_FILE)) and not args.force:
        print(f"{directory} already has a CA ({CA_FILE}); nothing changed. --force replaces it and every "
              "certificate (each machine then needs the new files)")
        return 1
    if args.days <= 0:
        print(f"error: --days must be positive, got {args.days:g}")
        return 2
    hosts = tuple(args.host or ("localhost", "127.0.0.1", socket.gethostname()))
    os.makedirs(directory, mode=0o700, exist_ok=True)
    ca = make_ca()
    write_public(os.path.join(directory, CA_FILE), ca.cert_pem)
    write_private(os.path.join(directory, CA_KEY_FILE), ca.key_pem)
    names = identities()
    for name in names:
        issued = issue(ca, name, hosts=hosts, days=args.days)
        write_public(os.path.join(directory, cert_file(name)), issued.cert_pem)
        write_private(os.path.join(directory, key_file(name)), issued.key_pem)
    routers = write_router_configs(directory)
    print(f"secure bus credentials in {directory}:")
    print(f"  {CA_FILE} (the CA: copy to every machine), {CA_KEY_FILE} (0600: keep it here, never copy it)")
    print(f"  certificate + key (0600) for: {', '.join(names)}; valid {args.days:g} days; hosts {', '.join(hosts)}")
    print(f"  router configs: {', '.join(routers)}")
    print("use: neso up --secure   (other machines: docs/secure-bus.md, 'A second machine')")
    return 0

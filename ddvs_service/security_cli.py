"""`ddvs security init --robot NAME [--robot NAME2 ...] [--process NAME] [--roles R1,R2,...] OUT/`: secure the Zenoh
network of one robot, or of a fleet (the robots one `ddvs serve` process serves), in one step.

Writes into `OUT/` (docs/security.md, "Securing a robot"):
- the certificates per purpose (`protocol/pki.py`), all of this robot's own CA: `ca/`, `router/` (serverAuth, the
  router endpoint's host among its names, CN `router@<prefix>/<NAME>`), one directory per role (clientAuth, CN
  `<role>@<prefix>/<NAME>`);
- `router/passwords.txt` (a random password per user `<role>@<prefix>/<NAME>`, owner-only) for the user/password
  variant;
- every configuration (`protocol/security.py::write_configs`): `router-mtls.json5`, `router-password.json5` and per
  role `<role>-mtls.json5`, `<role>-password.json5` (with its password, owner-only), all for robot `<prefix>/<NAME>`.

ROS 2 mode (docs/ros2.md): `--ros-domain-id N [--ros-namespace NS] [--ros-topic ROW:=NAME ...]`, as the nodes will
run, adds the rules for the rmw_zenoh keys of the ROS topics, the service node's Trigger services (served by the
service, called by the operator) and the ROS graph (each role holds the graph tokens of its own nodes, every role
watches the domain's); the JSON keys stay as in plain mode.

A fleet: `--robot A --robot B`, the robots `ddvs serve --robots A B` serves; each role gets the same grants on every
robot's keys, and the service and the operator the command key of the process (`<prefix>/serve/<process>/command`,
`--process`, default: the first robot, as `ddvs serve` names it).

Paths inside the configurations are `OUT/...` as given: run the nodes from the directory `ddvs security init` ran in
(or give an absolute OUT, or `--certs-dir` for where the files will be installed). Idempotent: existing certificates
and passwords are kept. One OUT holds one robot's (or one fleet's) files: an OUT holding another robot's CA or
configurations is refused, never reused (a fleet's scope is `<prefix>/<process>`). `--configs-only` writes the
configurations with `CHANGE-ME-<role>` passwords and issues nothing (how `configs/security/` is made: `ddvs security
init --robot robot0 --certs-dir certs --configs-only configs/security`).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.protocol.ros_cli import add_ros_arguments

    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    init = sub.add_parser("init", help="certificates, passwords and every Zenoh configuration for a robot or a fleet",
                          description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    init.add_argument("out_dir", metavar="OUT", help="directory to write (created if needed)")
    init.add_argument("--robot", dest="robots", action="append", metavar="NAME",
                      help="robot name in the keys (`<prefix>/<robot>/...`); repeated: a fleet, the robots one "
                           "`ddvs serve --robots ...` serves")
    init.add_argument("--process", metavar="NAME",
                      help="name of the `ddvs serve` process serving the robots, in its command key "
                           "<prefix>/serve/NAME/command (default: the first robot, as `ddvs serve` names it)")
    init.add_argument("--prefix", default="ddvs", help="key prefix (default ddvs)")
    init.add_argument("--roles", action="append", metavar="ROLE,...",
                      help="roles to create, comma-separated or repeated (default: every role: "
                           "service,plant,bridge,operator,observer)")
    init.add_argument("--router", default="tls/localhost:7447",
                      help="the hub router's endpoint as the nodes reach it (default tls/localhost:7447)")
    init.add_argument("--certs-dir", metavar="DIR", help="where the nodes find the certificate directories "
                      "(default: OUT as given)")
    init.add_argument("--no-observer-frames", action="store_true",
                      help="observers may not read camera frames nor the reference image")
    init.add_argument("--configs-only", action="store_true",
                      help="write the configurations only (placeholder passwords, no certificates)")
    add_ros_arguments(init)  # rules for the nodes' ROS 2 mode: give the options the nodes will run with


def _passwords(path: Path, users: list[str]) -> dict[str, str]:
    """The router's password file `path` (lines `user:password`), completed with a random password per missing user."""
    import secrets

    known: dict[str, str] = {}
    if path.is_file():
        for line in path.read_text(encoding="utf-8").splitlines():
            user, sep, password = line.partition(":")
            if sep:
                known[user] = password
    for user in users:
        known.setdefault(user, secrets.token_urlsafe(24))
    path.write_text("".join(f"{user}:{password}\n" for user, password in known.items()), encoding="utf-8")
    path.chmod(0o600)
    return known


def _refuse_another_robots(out: Path, scope: str) -> None:
    """ValueError when `out` already holds another robot's CA or router configurations: one directory, one robot (or
    fleet), so that re-running init never mixes two robots' certificates or rules."""
    from ddvs_service.protocol.pki import check_ca
    from ddvs_service.protocol.security import configured_scopes

    if (out / "ca" / "ca.pem").is_file():
        check_ca(out / "ca" / "ca.pem", scope)
    others = sorted(configured_scopes(out) - {scope})
    if others:
        raise ValueError(f"{out} holds the configurations of {', '.join(others)}, not of {scope}: each robot's files "
                         f"go into their own directory; give another OUT for {scope}")


def run(args: argparse.Namespace) -> int:
    from ddvs_service.protocol.keys import Keys
    from ddvs_service.protocol.pki import DEFAULT_ROUTER_NAMES, issue_certificates
    from ddvs_service.protocol.ros_cli import ros_settings_from_args
    from ddvs_service.protocol.security import ROLES, Endpoint, Fleet, identity_name, write_configs

    roles = [r for item in args.roles or [",".join(ROLES)] for r in item.replace(",", " ").split()]
    try:
        unknown = [r for r in roles if r not in ROLES]
        if unknown or not roles:
            raise ValueError(f"roles {unknown or roles}: expected some of {', '.join(ROLES)}")
        if not args.robots:
            raise ValueError("no robot: give --robot NAME (repeated for a fleet: --robot A --robot B)")
        ros = ros_settings_from_args(args)
        fleet = Fleet(tuple(Keys(args.prefix, robot, ros) for robot in args.robots), args.process or "")
        host = Endpoint.parse(args.router).host
        cert_dir = args.certs_dir or args.out_dir.rstrip("/")
        out = Path(args.out_dir)
        _refuse_another_robots(out, fleet.scope)
        passwords = None
        if not args.configs_only:
            names = list(dict.fromkeys([host, *DEFAULT_ROUTER_NAMES]))
            for path in issue_certificates(out, roles, fleet.scope, names):
                print(f"created {path}")
            users = {role: identity_name(role, fleet.scope) for role in roles}
            known = _passwords(out / "router" / "passwords.txt", list(users.values()))
            passwords = {role: known[user] for role, user in users.items()}
        written = write_configs(out, fleet, cert_dir, args.router, roles, passwords,
                                observers_read_frames=not args.no_observer_frames)
    except (RuntimeError, ValueError) as exc:
        raise SystemExit(f"ddvs security init: {exc}") from None
    for path in written:
        print(f"wrote {path}")
    configs = args.out_dir.rstrip("/")
    nodes = (f"`--mode client --connect {args.router} --zenoh-config {configs}/<role>-mtls.json5 --prefix "
             f"{args.prefix}")
    if ros.enabled:
        remaps = "".join(f" --ros-topic {row}:={name}" for row, name in ros.topics.items())
        nodes += f" --ros-domain-id {ros.domain_id} --ros-namespace {ros.namespace}{remaps}"
    if len(fleet.robots) == 1 and fleet.process == fleet.robots[0].robot:
        nodes += f" --robot {fleet.robots[0].robot}`"
    else:
        process = "" if fleet.process == fleet.robots[0].robot else f" --process {fleet.process}"
        nodes += (f"`, then `ddvs serve --robots {' '.join(k.robot for k in fleet.robots)}{process}` and each "
                  f"robot's other nodes `--robot NAME`")
    print(f"{fleet.describe()}: from this directory, start the router with `ddvs router --zenoh-config "
          f"{configs}/router-mtls.json5 --listen {args.router}` and each node with {nodes}")
    return 0

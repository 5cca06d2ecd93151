"""`ddvs ctl`: send one control-plane `Command` to the servo service and print its JSON `Reply`.

The command travels as the payload of a Zenoh query on `keys.servo_command` (`…/servo/command`); the first reply is
parsed as a `Reply` (docs/protocol.md). Exit status: 0 when the reply is ok, 1 when the service refused the command
(the reply's `error` says why), 2 when no reply arrived within `--timeout` seconds (no service, or too slow).

Actions: `set-reference (--next-frame | --image FILE) [--roi X Y W H]`, `start`, `stop`, `reset`, `state`,
`config get`, `config set (--set key.path=value ... | --file JSON)`. `--set` values are parsed as JSON when they
are valid JSON (numbers, true/false, lists, objects) and kept as strings otherwise.

Process actions (one `ddvs serve` serving several robots) go to the process's key
`<prefix>/serve/<process>/command` (`--process`, default the `--robot` name: a process is named after its first
robot): `add-robot NAME [--set key.path=value ... | --file JSON] [--fresh]`, `remove-robot NAME`, `robots`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import zenoh

    from ddvs_service.protocol import Command, Keys, Reply

EXIT_OK, EXIT_REFUSED, EXIT_NO_REPLY = 0, 1, 2


def dotted_patch(assignments: list[str]) -> dict[str, Any]:
    """Nested configuration patch from `key.path=value` strings, e.g. `control.law=ddvs` → `{"control": {"law":
    "ddvs"}}`. Values are JSON when they parse as JSON, else plain strings."""
    patch: dict[str, Any] = {}
    for item in assignments:
        path, sep, text = item.partition("=")
        keys = path.strip().split(".")
        if not sep or not all(keys):
            raise ValueError(f"--set {item!r}: expected key.path=value, e.g. control.gains=0.4")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        node = patch
        for key in keys[:-1]:
            child = node.setdefault(key, {})
            if not isinstance(child, dict):
                raise ValueError(f"--set {item!r}: {key!r} was already given a value, it cannot also hold keys")
            node = child
        node[keys[-1]] = value
    return patch


def command_from_args(args: argparse.Namespace) -> Command:
    """The `Command` an action's arguments describe (raises `ValueError` on unusable arguments)."""
    from ddvs_service.protocol import Command, ReferenceImage, Roi, encode_upload

    action = args.action
    if action == "set-reference":
        roi = Roi(x=args.roi[0], y=args.roi[1], width=args.roi[2], height=args.roi[3]) if args.roi else None
        if args.image is None:
            return Command(op="set_reference", source="next_frame", roi=roi)
        import cv2

        image = cv2.imread(str(args.image), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"cannot read reference image {args.image} (missing, or a format OpenCV cannot decode)")
        upload = ReferenceImage(format="png", data=encode_upload(image, "png"))
        return Command(op="set_reference", source="upload", image=upload, roi=roi)
    if action in ("start", "stop", "reset"):
        return Command(op=action)
    if action == "state":
        return Command(op="get_state")
    if action == "robots":
        return Command(op="list_robots")
    if action == "remove-robot":
        return Command(op="remove_robot", robot=args.name)
    if action == "add-robot":
        return Command(op="add_robot", robot=args.name, config=_patch(args) or None, fresh=args.fresh)
    if args.config_action == "get":
        return Command(op="get_config")
    patch = _patch(args)
    if not patch:
        raise ValueError("config set needs --set key.path=value (repeatable) or --file JSON")
    return Command(op="set_config", config=patch)


def _patch(args: argparse.Namespace) -> dict[str, Any]:
    """The configuration patch of `--file JSON` or of the `--set` assignments (empty without either)."""
    if args.file is None:
        return dotted_patch(args.set or [])
    patch = json.loads(Path(args.file).read_text(encoding="utf-8"))
    if not isinstance(patch, dict):
        raise ValueError(f"{args.file} holds a JSON {type(patch).__name__}; expected an object")
    return patch


def command_key(keys: Keys, command: Command, process: str | None = None) -> str:
    """Where `command` goes: the robot's `servo/command`, or for a process command the key of `process` (default:
    the robot's name, the default name of a process whose first robot it is)."""
    from ddvs_service.protocol.control import PROCESS_OPS, process_command_key

    if command.op in PROCESS_OPS:
        return process_command_key(keys.prefix, process or keys.robot)
    return keys.servo_command


def send_command(session: zenoh.Session, keys: Keys, command: Command, timeout: float = 5.0,
                 process: str | None = None) -> Reply | None:
    """Query the service with `command` (on `command_key`); its `Reply`, a failure `Reply` for a Zenoh error reply
    or an unparsable answer, or None when nothing answered within `timeout` seconds."""
    from ddvs_service.protocol import InvalidMessage, Reply, dump, parse_message

    for answer in session.get(command_key(keys, command, process), payload=dump(command), timeout=timeout):
        sample = answer.ok
        if sample is None:  # then the answer is a Zenoh error reply
            error = "" if answer.err is None else answer.err.payload.to_string()
            return Reply.failure(f"the service answered with a Zenoh error: {error}")
        try:
            return parse_message(Reply, sample.payload.to_bytes())
        except InvalidMessage as exc:
            return Reply.failure(f"the service's reply is not a valid Reply: {exc}")
    return None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.protocol import add_zenoh_arguments

    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the reply (default 5)")
    parser.add_argument("--prefix", default="ddvs", help="key prefix (default ddvs)")
    parser.add_argument("--robot", default="robot0", help="robot name in the keys (default robot0)")
    parser.add_argument("--process", help="the serving process's name, for add-robot, remove-robot and robots "
                                          "(default: the --robot name)")
    add_zenoh_arguments(parser)
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    ref = actions.add_parser("set-reference", help="set the reference image I* (next camera frame or a file)")
    source = ref.add_mutually_exclusive_group(required=True)
    source.add_argument("--next-frame", action="store_true", help="use the next camera frame")
    source.add_argument("--image", type=Path, help="upload this image file (PNG, JPEG, …; grey or colour)")
    ref.add_argument("--roi", type=int, nargs=4, metavar=("X", "Y", "W", "H"),
                     help="template rectangle in reference pixels (default: the service's template around p*)")
    for name, help_text in (("start", "start servoing"), ("stop", "stop servoing (zero twist)"),
                            ("reset", "forget the reference"), ("state", "print the service state")):
        actions.add_parser(name, help=help_text)
    config = actions.add_parser("config", help="get or set the service configuration")
    config_actions = config.add_subparsers(dest="config_action", metavar="get|set", required=True)
    config_actions.add_parser("get", help="print the configuration")
    _add_patch_arguments(config_actions.add_parser("set", help="change part of the configuration"), required=True)
    add = actions.add_parser("add-robot", help="serve one more robot in the process (process command)")
    add.add_argument("name", help="the robot's name in its keys")
    _add_patch_arguments(add, required=False)
    add.add_argument("--fresh", action="store_true", help="delete the robot's persisted state first")
    actions.add_parser("remove-robot", help="stop serving a robot (process command)").add_argument(
        "name", help="the robot's name")
    actions.add_parser("robots", help="list the process's robots (process command)")


def _add_patch_arguments(parser: argparse.ArgumentParser, required: bool) -> None:
    patch = parser.add_mutually_exclusive_group(required=required)
    patch.add_argument("--set", action="append", metavar="KEY.PATH=VALUE", help="one setting (repeatable)")
    patch.add_argument("--file", type=Path, help="JSON file with a (partial) configuration object")


def run(args: argparse.Namespace) -> int:
    from ddvs_service.protocol import Keys, open_session, session_config_from_args

    try:
        command = command_from_args(args)
    except (ValueError, OSError) as exc:
        print(f"ddvs ctl: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    keys = Keys(args.prefix, args.robot)
    with open_session(session_config_from_args(args)) as session:
        reply = send_command(session, keys, command, args.timeout, args.process)
    if reply is None:
        print(f"ddvs ctl: no reply on {command_key(keys, command, args.process)} within {args.timeout} s (is "
              "`ddvs serve` running and reachable with these Zenoh settings?)", file=sys.stderr)
        return EXIT_NO_REPLY
    print(reply.model_dump_json(indent=2))
    return EXIT_OK if reply.ok else EXIT_REFUSED

"""JSON control plane: commands, replies, status, state snapshots and ground truth, validated with pydantic.

Every message carries `protocol_version` (= `PROTOCOL_VERSION`); unknown fields are rejected (`extra="forbid"`),
and non-finite floats too. Units: times in integer nanoseconds since the Unix epoch (`*_ns`), latencies in
milliseconds, twists `[v (m/s); ω (rad/s)]` in the current camera frame, pixels as in `ddvs_service.camera`.
The error vector `e` and `error_norm` are the decoupled servo error of docs/equations.md (eq. numbers there).

Commands travel as the payload of a Zenoh query on `…/servo/command` (a robot's commands) or, for the process
commands `PROCESS_OPS` (which robots one `ddvs serve` process serves), on `process_command_key(prefix, process)`; the
reply is a `Reply`.
`parse_command` / `parse_message` turn bytes into models and raise only `InvalidMessage`; `dump` is the inverse.
JSON schemas of these models are committed under `ddvs_service/schemas/` (see `schemas.py`).
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Final, Literal, TypeVar, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ddvs_service.protocol.errors import InvalidMessage
from ddvs_service.protocol.ros import IMAGE_MAX_BYTES
from ddvs_service.protocol.upload import UploadFormat, decode_upload

PROTOCOL_VERSION: Final = 1
COMMAND_MAX_BYTES = 16 << 20
"""Bound on a JSON message (a 1920×1080 float32 .npy reference upload is ≈ 11 MiB in base64)."""

ServoStateName = Literal["IDLE", "READY", "SERVOING", "CONVERGED", "LOST", "STOPPED"]
CommandOp = Literal["set_reference", "start", "stop", "reset", "get_state", "get_config", "set_config",
                    "add_robot", "remove_robot", "list_robots"]
COMMAND_OPS: tuple[str, ...] = get_args(CommandOp)
PROCESS_OPS: tuple[str, ...] = ("add_robot", "remove_robot", "list_robots")
"""Commands of a `ddvs serve` process, answered on its process key, not on a robot's `…/servo/command`."""
Vector6 = Annotated[list[float], Field(min_length=6, max_length=6)]
NonNegative = Annotated[float, Field(ge=0.0)]
Count = Annotated[int, Field(ge=0)]


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


class Roi(_Message):
    """Rectangle of interest in pixels: top-left corner column `x`, row `y`, size `width` × `height`."""

    x: Count
    y: Count
    width: Annotated[int, Field(gt=0)]
    height: Annotated[int, Field(gt=0)]


class ReferenceImage(_Message):
    """An uploaded image: base64 of a PNG file (8/16-bit) or of a `.npy` file (uint8/uint16/float32/float64)."""

    format: UploadFormat
    data: str

    def to_array(self, max_bytes: int = IMAGE_MAX_BYTES) -> Any:
        """Decoded numpy image of at most `max_bytes` bytes; raises `InvalidMessage` or `MessageTooLarge` (the
        decoded size is checked before decoding)."""
        return decode_upload(self.data, self.format, max_bytes)


def process_command_key(prefix: str, process: str) -> str:
    """The key of a `ddvs serve` process's commands (`PROCESS_OPS`): `<prefix>/serve/<process>/command`."""
    return f"{prefix}/serve/{process}/command"


class Command(_Message):
    """A request to the servo service.

    - `set_reference`: `source` "next_frame" (use the next camera frame) or "upload" (with `image`); optional `roi`.
    - `start`, `stop`, `reset`, `get_state`, `get_config`: no arguments.
    - `set_config`: `config`, a (partial) configuration object validated by the service.
    - `add_robot` (process): `robot`, the name to serve; optional `config`, that robot's settings over the process's
      configuration; `fresh` true ignores (and deletes) the robot's persisted state.
    - `remove_robot` (process): `robot`. `list_robots` (process): no arguments.
    `id` is an optional client tag echoed in logs.
    """

    protocol_version: Literal[1] = PROTOCOL_VERSION
    op: CommandOp
    id: Annotated[str, Field(max_length=128)] | None = None
    source: Literal["next_frame", "upload"] | None = None
    image: ReferenceImage | None = None
    roi: Roi | None = None
    config: dict[str, Any] | None = None
    robot: Annotated[str, Field(min_length=1, max_length=256)] | None = None
    fresh: bool = False

    @model_validator(mode="after")
    def _arguments_match_op(self) -> Command:
        if self.op == "set_reference":
            if self.source is None:
                raise ValueError("set_reference needs 'source': 'next_frame' or 'upload'")
            if (self.source == "upload") != (self.image is not None):
                raise ValueError("set_reference takes 'image' exactly when source is 'upload'")
        elif self.source is not None or self.image is not None or self.roi is not None:
            raise ValueError(f"'source', 'image' and 'roi' belong to set_reference, not to {self.op}")
        if self.op == "set_config" and self.config is None:
            raise ValueError("'config' is required by set_config")
        if self.config is not None and self.op not in ("set_config", "add_robot"):
            raise ValueError(f"'config' belongs to set_config and add_robot, not to {self.op}")
        if (self.op in ("add_robot", "remove_robot")) != (self.robot is not None):
            raise ValueError(f"'robot' is required by add_robot and remove_robot and not allowed with {self.op}"
                             if self.robot is not None else f"{self.op} needs 'robot': the robot's name")
        if self.fresh and self.op != "add_robot":
            raise ValueError(f"'fresh' belongs to add_robot, not to {self.op}")
        return self


class Reply(_Message):
    """The answer to a `Command`: `ok` with optional `data`, or not ok with a non-empty `error`."""

    protocol_version: Literal[1] = PROTOCOL_VERSION
    ok: bool
    error: str | None = None
    data: dict[str, Any] | None = None

    @model_validator(mode="after")
    def _error_iff_failed(self) -> Reply:
        if self.ok == bool(self.error):
            raise ValueError("a Reply has a non-empty 'error' exactly when ok is false")
        return self

    @classmethod
    def success(cls, data: dict[str, Any] | None = None) -> Reply:
        return cls(ok=True, data=data)

    @classmethod
    def failure(cls, error: str) -> Reply:
        return cls(ok=False, error=error)


class Latency(_Message):
    """Per-frame processing times in milliseconds (`total` from payload arrival to twist published), and `cpu`, the
    service process's CPU time over the frame's work (decode to publish, all its threads): work far longer than
    `cpu` is time the host did not run the service (other processes on its cores), not work of the service."""

    decode: NonNegative
    registration: NonNegative
    control: NonNegative
    publish: NonNegative
    total: NonNegative
    cpu: NonNegative = 0.0


class Counters(_Message):
    """Frames since the service started, each counted once, none ever decreasing: `frames` processed (registered),
    `dropped` (superseded by a newer valid frame before processing), `rejected` (failed to decode or validate, counted
    as they arrive; camera infos too), `stale` (processed, but the twist withheld: it would have gone out more than
    `frame_timeout_s` after the frame arrived with two newer frames waiting, or the frame is older than a twist
    already published; also in `frames`) and `idle` (arrived while IDLE, not answered)."""

    frames: Count
    dropped: Count
    rejected: Count
    stale: Count = 0
    idle: Count = 0


class Status(_Message):
    """Published on `…/servo/status` after every processed frame."""

    protocol_version: Literal[1] = PROTOCOL_VERSION
    robot: str
    state: ServoStateName
    frame_stamp_ns: int
    seq: Count
    error: Vector6
    error_norm: NonNegative
    iterations: Count
    residual_rms: NonNegative
    inlier_ratio: Annotated[float, Field(ge=0.0, le=1.0)]
    twist: Vector6
    latency_ms: Latency
    counters: Counters
    message: str = ""
    backend: str = ""  # the Taichi backend the kernels run on ('cpu', 'vulkan', 'cuda'; '' when not reported)


class StateSnapshot(_Message):
    """Published on `…/servo/state` on every state change and returned by `get_state`.

    `homography`: the current reference→current pixel homography, row-major 3×3 with H[2,2] = 1 (None without one).
    """

    protocol_version: Literal[1] = PROTOCOL_VERSION
    robot: str
    state: ServoStateName
    has_reference: bool
    reference_stamp_ns: int | None = None
    roi: Roi | None = None
    homography: Annotated[list[float], Field(min_length=9, max_length=9)] | None = None
    last_status: Status | None = None
    message: str = ""


class GroundTruth(_Message):
    """Evaluation only (`…/arm/ground_truth`): the true camera pose from a simulator at `stamp_ns`.

    `camera_pose`: row-major 4×4 homogeneous transform from the camera frame (OpenCV axes) to `frame_id`, metres.
    """

    protocol_version: Literal[1] = PROTOCOL_VERSION
    stamp_ns: int
    frame_id: str = "world"
    camera_pose: Annotated[list[float], Field(min_length=16, max_length=16)]
    joint_positions: list[float] | None = None


M = TypeVar("M", bound=BaseModel)


def _reject_constant(name: str) -> None:
    raise ValueError(f"{name} is not valid JSON")


def _load_object(buf: bytes | bytearray | memoryview | str, max_bytes: int) -> dict[str, Any]:
    if len(buf) > max_bytes:
        raise InvalidMessage(f"message is {len(buf)} bytes; the maximum is {max_bytes}")
    try:
        text = buf if isinstance(buf, str) else bytes(buf).decode("utf-8")
        obj = json.loads(text, parse_constant=_reject_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise InvalidMessage(f"message is not valid JSON: {exc}") from exc
    if not isinstance(obj, dict):
        raise InvalidMessage(f"message is a JSON {type(obj).__name__}; expected an object")
    version = obj.get("protocol_version")
    if version != PROTOCOL_VERSION or isinstance(version, bool):
        found = "missing" if "protocol_version" not in obj else f"{version!r}"
        raise InvalidMessage(f"protocol_version is {found}; expected {PROTOCOL_VERSION}")
    return obj


def _validate(model: type[M], obj: dict[str, Any]) -> M:
    try:
        return model.model_validate(obj)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc']) or '<message>'}: {e['msg']}" for e in exc.errors()[:5]
        )
        raise InvalidMessage(f"invalid {model.__name__}: {problems}") from None


def parse_message(model: type[M], buf: bytes | bytearray | memoryview | str, max_bytes: int = COMMAND_MAX_BYTES) -> M:
    """Parse and validate a JSON message of type `model`; raises only `InvalidMessage` (a `ProtocolError`)."""
    return _validate(model, _load_object(buf, max_bytes))


def parse_command(buf: bytes | bytearray | memoryview | str, max_bytes: int = COMMAND_MAX_BYTES) -> Command:
    """Parse a `Command`; errors name the problem (bad JSON, wrong version, unknown op, wrong types, oversize)."""
    obj = _load_object(buf, max_bytes)
    op = obj.get("op")
    if op not in COMMAND_OPS:
        found = "missing" if "op" not in obj else f"{op!r}"
        raise InvalidMessage(f"op is {found}; expected one of {', '.join(COMMAND_OPS)}")
    return _validate(Command, obj)


def dump(model: BaseModel) -> bytes:
    """UTF-8 JSON bytes of a message (fields set to None are written as null)."""
    return model.model_dump_json().encode("utf-8")

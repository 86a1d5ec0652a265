"""Wire protocol 1.2 of `photoreg serve` (docs/protocol.md): framing, message builders, validation.

Pure functions, no I/O: the server and the client both build and check messages here, so the two
sides cannot drift apart. A message is either a WebSocket text message holding one JSON object, or
a binary message: a 4-byte big-endian header length, that many bytes of UTF-8 JSON header, then
payload bytes that the header addresses by (offset, length) relative to the payload start.
Every check raises ProtocolError(code, message) naming the field at fault.
"""
from __future__ import annotations

import json
import math
import os
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..config import LightingConfig, ObjectConfig, ReconstructionConfig, RenderConfig, Session, _fill, validate
from ..io.images import COLOR_FLAGS, after_fill, jpeg_cut_short, registered_depth
from ..io.intrinsics import checked_intrinsics
from ..io.native import depth_to_png16
from ..io.poses import check_pose
from ..types import Frame, Intrinsics

# 1.1: composites of the hello's objects (1.0 accepted objects, sent none); 1.2: frame.shutter, frame.depth.width and
# height (depth at its own size), lighting.pose (the camera pose the server had: the client's, or tracked)
PROTOCOL_VERSION = "1.2"
MAJOR = 1
CLIENT_TYPES = ("hello", "frame", "bye")
COLOR_ENCODINGS = ("jpeg", "png", "rgb8")    # rgb8: H*W*3 bytes, row-major, R G B
DEPTH_ENCODINGS = ("png16", "u16", "f32")    # u16: little-endian depth_scale units; f32: little-endian metres
COMPOSITE_ENCODINGS = ("jpeg", "png")        # of the composites the server sends (8-bit sRGB); jpeg the default
JPEG_QUALITY = 90
MESH_SUFFIXES = (".ply", ".obj", ".off", ".glb", ".gltf", ".stl")   # what the meshes folder lists as its meshes
ERROR_CODES = ("bad_message", "unknown_type", "missing_field", "bad_field", "bad_image", "too_large", "version",
               "not_ready", "already_ready", "unauthorized", "too_many_clients", "pipeline", "idle_timeout",
               "shutting_down", "internal")
# Keys a lighting reply adds to the lighting.jsonl record (runner.result_record).
LIGHTING_EXTRA = ("type", "dropped", "latency_ms", "queue_ms")
# Reconstruction keys a client may set; block_count (memory) stays the server's.
CLIENT_RECONSTRUCTION_KEYS = ("voxel_size", "trunc_voxels", "depth_min", "depth_max", "depth_filter_px",
                              "depth_filter_m", "normal_smoothing_voxels")
_LEN = struct.Struct(">I")
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


class ProtocolError(ValueError):
    """A message the other side got wrong, or an error reply received: code from ERROR_CODES."""

    def __init__(self, code: str, message: str, frame: int | None = None):
        super().__init__(message)
        self.code, self.message, self.frame = code, message, frame

    def __str__(self) -> str:
        return f"{self.code}: {self.message}"

    def to_message(self) -> dict:
        return error_message(self.code, self.message, self.frame)


@dataclass(frozen=True)
class Limits:
    """What one connection may ask of the server (announced in `ready`)."""

    max_message_bytes: int = 32 * 2**20
    max_width: int = 4096
    max_height: int = 4096
    max_pixels: int = 4096 * 2304
    max_rays: int = 1024
    max_stride: int = 64
    min_voxel_size: float = 0.005   # metres: finer volumes cost memory the server does not promise
    max_trunc_voxels: float = 16.0  # wider truncation bands touch more blocks per frame
    max_depth: float = 10.0         # metres (reconstruction.depth_max): farther depth touches more blocks
    max_objects: int = 32
    # the light search's and the solves' sizes (their memory and time grow with them; defaults 256, 8 and 16, 8000)
    max_sun_candidates: int = 4096  # lighting.sun_candidates
    max_light_rays: int = 64        # lighting.sun_rays, render.light_rays
    max_samples: int = 50000        # lighting.max_samples, sun_samples, history

    def to_json(self) -> dict:
        return dict(vars(self))


@dataclass
class Hello:
    """A validated `hello`: the session it asks for (server defaults plus the client's overrides)."""

    version: str
    intrinsics: Intrinsics
    session: Session
    token: str | None
    notes: list[str] = field(default_factory=list)
    composite: str = COMPOSITE_ENCODINGS[0]   # encoding of the composite messages (when the session has objects)


# ---------------------------------------------------------------------------------------------- framing

def encode(header: dict, payload: bytes = b"") -> str | bytes:
    """A message: JSON text when there is no payload, else the binary framing (length, header, payload)."""
    text = json.dumps(header, allow_nan=False, separators=(",", ":"))
    if not payload:
        return text
    head = text.encode()
    return b"".join((_LEN.pack(len(head)), head, payload))


def decode(data: str | bytes) -> tuple[dict, memoryview]:
    """(header, payload) of a text or binary message; the header is a JSON object with a string `type`."""
    payload = memoryview(b"")
    if isinstance(data, str):
        text = data
    else:
        view = memoryview(data)
        if len(view) < _LEN.size:
            raise ProtocolError("bad_message", f"binary message of {len(view)} bytes is shorter than its "
                                               "4-byte header length")
        n = _LEN.unpack(view[:_LEN.size])[0]
        if n > len(view) - _LEN.size:
            raise ProtocolError("bad_message", f"header length {n} exceeds the {len(view) - _LEN.size} bytes "
                                               "that follow it")
        try:
            text = bytes(view[_LEN.size:_LEN.size + n]).decode()
        except UnicodeDecodeError:
            raise ProtocolError("bad_message", "header is not UTF-8 text") from None
        payload = view[_LEN.size + n:]
    try:
        header = json.loads(text)
    except (ValueError, RecursionError) as e:   # ValueError: also an integer past Python's 4300 digits
        why = "nested too deeply" if isinstance(e, RecursionError) else getattr(e, "msg", None) or str(e)[:80]
        raise ProtocolError("bad_message", f"header is not valid JSON ({why})") from None
    if not isinstance(header, dict):
        raise ProtocolError("bad_message", f"header must be a JSON object, got {type(header).__name__}")
    kind = header.get("type")
    if not isinstance(kind, str):
        raise ProtocolError("missing_field" if kind is None else "bad_field",
                            "message needs a string field 'type'")
    return header, payload


def token_option(given: str | None) -> str | None:
    """The token of --token, else $PHOTOREG_TOKEN, else none; an empty one is refused (it would turn the check off)."""
    token, where = (given, "--token") if given is not None else (os.environ.get("PHOTOREG_TOKEN"), "PHOTOREG_TOKEN")
    if token is not None and not token.strip():
        raise ValueError(f"{where} is empty: give a token, or leave it unset for none")
    return token


# ---------------------------------------------------------------------------------------------- builders

def hello_message(intrinsics: Intrinsics, options: dict | None = None, token: str | None = None,
                  composite: str | None = None) -> dict:
    msg = {"type": "hello", "version": PROTOCOL_VERSION, "intrinsics": intrinsics.to_json(),
           "options": options or {}}
    if token is not None:
        msg["token"] = token
    if composite is not None:
        msg["composite"] = composite
    return msg


def ready_message(hello: Hello, device: str, queue: int, limits: Limits) -> dict:
    s = hello.session
    return {"type": "ready", "version": PROTOCOL_VERSION, "device": device, "queue": queue,
            "intrinsics": hello.intrinsics.to_json(),
            "settings": {"lighting": vars(s.lighting), "reconstruction": vars(s.reconstruction),
                         "use_poses": s.recording.use_poses, "shadows": s.render.shadows, "render": vars(s.render),
                         "objects": len(s.objects), "composite": hello.composite if s.objects else None},
            "compositing": bool(s.objects), "limits": limits.to_json(), "notes": list(hello.notes)}


def lighting_message(record: dict, dropped: int, latency_ms: float, queue_ms: float) -> dict:
    """Reply to one processed frame: the lighting.jsonl record plus backpressure and latency figures."""
    return {"type": "lighting", **record, "dropped": int(dropped), "latency_ms": round(latency_ms, 3),
            "queue_ms": round(queue_ms, 3)}


def record_from_lighting(msg: dict) -> dict:
    """The lighting.jsonl record inside a lighting reply (what `photoreg run` would have written)."""
    return {k: v for k, v in msg.items() if k not in LIGHTING_EXTRA}


def _encode_rgb8(rgb8: np.ndarray, encoding: str, jpeg_quality: int, what: str) -> bytes:
    """PNG or JPEG bytes of an 8-bit RGB image (`encoding` "png" or "jpeg"); `what` names it in the error."""
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if encoding == "jpeg" else []
    ok, buf = cv2.imencode(".jpg" if encoding == "jpeg" else ".png", cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise ValueError(f"{what}: could not encode it as {encoding}")
    return buf.tobytes()


def encode_composite(image: np.ndarray, encoding: str) -> bytes:
    """A composite (H, W, 3 8-bit sRGB, RGB order) as the image bytes of a `composite` message: PNG lossless (the
    pixels of `photoreg run`'s composite/NNNNNN.png), JPEG at JPEG_QUALITY."""
    return _encode_rgb8(image, encoding, JPEG_QUALITY, "the composite")


def composite_message(index: int, image: bytes, encoding: str) -> bytes:
    """The binary `composite` message of frame `index` (sent after its `lighting` reply)."""
    return encode({"type": "composite", "frame": int(index),
                   "image": {"encoding": encoding, "offset": 0, "length": len(image)}}, image)


def decode_composite(header: dict, payload: memoryview) -> tuple[int, str, bytes]:
    """(frame index, encoding, image bytes) of a received `composite` message."""
    index = _count(_get(header, "frame", "composite"), "composite.frame")
    encoding, image = _payload(_get(header, "image", "composite"), "image", payload, COMPOSITE_ENCODINGS, "composite")
    return index, encoding, image


def error_message(code: str, message: str, frame: int | None = None) -> dict:
    msg = {"type": "error", "code": code, "message": message}
    if frame is not None:
        msg["frame"] = frame
    return msg


def bye_message(reason: str, **stats) -> dict:
    return {"type": "bye", "reason": reason, **stats}


def encode_frame(frame: Frame, index: int | None = None, color: str = "png", depth: str = "png16",
                 jpeg_quality: int = 95) -> bytes:
    """A binary `frame` message. png colour is lossless; png16/u16 depth is lossless for frames read from
    16-bit depth files at the intrinsics' depth_scale (depth beyond 65535 units becomes invalid); f32 is
    lossless for any depth. A frame whose depth is registered at a lower resolution (`frame.depth_native`) sends
    it at that resolution (frame.depth's width and height), which the receiver scales up as the recording did."""
    if color not in COLOR_ENCODINGS:
        raise ValueError(f"colour encoding must be one of {COLOR_ENCODINGS}, got {color!r}")
    if depth not in DEPTH_ENCODINGS:
        raise ValueError(f"depth encoding must be one of {DEPTH_ENCODINGS}, got {depth!r}")
    if color == "rgb8":
        cbytes = np.ascontiguousarray(frame.color, dtype=np.uint8).tobytes()
    else:
        cbytes = _encode_rgb8(frame.color, color, jpeg_quality, f"frame {frame.index}: the colour image")
    metres = frame.depth if frame.depth_native is None else frame.depth_native
    if depth == "f32":
        dbytes = np.nan_to_num(metres, nan=0.0, posinf=0.0, neginf=0.0).astype("<f4").tobytes()
    else:
        raw = depth_to_png16(metres, frame.intrinsics.depth_scale)
        if depth == "u16":
            dbytes = raw.astype("<u2").tobytes()
        else:
            ok, buf = cv2.imencode(".png", raw)
            if not ok:
                raise ValueError(f"frame {frame.index}: could not encode the depth image as png16")
            dbytes = buf.tobytes()
    header = {"type": "frame", "index": frame.index if index is None else index, "timestamp": frame.timestamp,
              "pose": None if frame.pose is None else np.asarray(frame.pose, dtype=np.float64).tolist(),
              "color": {"encoding": color, "offset": 0, "length": len(cbytes)},
              "depth": {"encoding": depth, "offset": len(cbytes), "length": len(dbytes)}}
    if frame.depth_native is not None:
        header["depth"].update(width=metres.shape[1], height=metres.shape[0])
    if frame.shutter is not None:
        header["shutter"] = float(frame.shutter)
    return encode(header, cbytes + dbytes)


# ---------------------------------------------------------------------------------------------- validation

def _get(obj: dict, key: str, where: str):
    if key not in obj:
        raise ProtocolError("missing_field", f"{where}: missing field '{key}'")
    return obj[key]


MAX_INDEX = 2 ** 53   # integers a JSON number holds exactly in every client (JavaScript's safe integers)


def _number(value, name: str) -> float:
    try:   # an integer too large for a float (a 400-digit JSON number) is out of range like an infinity
        finite = not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)
    except OverflowError:
        finite = False
    if not finite:
        raise ProtocolError("bad_field", f"{name} must be a finite number, got {str(value):.80}")
    return float(value)


def _count(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < MAX_INDEX:
        raise ProtocolError("bad_field", f"{name} must be an integer in 0..2^53-1, got {str(value):.80}")
    return value


def _object(value, name: str) -> dict:
    if not isinstance(value, dict):
        raise ProtocolError("bad_field", f"{name} must be a JSON object, got {type(value).__name__}")
    return value


def check_version(version) -> str:
    """Accept any 1.x; anything else is a `version` error."""
    if not isinstance(version, str) or not re.match(r"[0-9]{1,6}(\.|$)", version):   # ASCII digits: int() takes them
        raise ProtocolError("bad_field", f"hello.version must be a string like \"{PROTOCOL_VERSION}\", "
                                         f"got {version!r:.80}")
    if int(version.partition(".")[0]) != MAJOR:
        raise ProtocolError("version", f"protocol version {version} is not supported: this server speaks "
                                       f"{PROTOCOL_VERSION} (major version {MAJOR})")
    return version


def parse_intrinsics(value, limits: Limits) -> Intrinsics:
    """hello.intrinsics {width, height, fx, fy, cx, cy[, depth_scale]}, within the server's size limits."""
    obj = _object(value, "hello.intrinsics")
    values = {"depth_scale": 1000.0}
    for key in ("width", "height", "fx", "fy", "cx", "cy", "depth_scale"):
        if key in obj or key != "depth_scale":
            values[key] = _number(_get(obj, key, "hello.intrinsics"), f"hello.intrinsics.{key}")
    unknown = sorted(set(obj) - set(values))
    if unknown:
        raise ProtocolError("bad_field", f"hello.intrinsics: unknown field(s) {', '.join(unknown)}")
    try:
        intr = checked_intrinsics(values, "hello.intrinsics")
    except ValueError as e:
        raise ProtocolError("bad_field", str(e)) from None
    if intr.width > limits.max_width or intr.height > limits.max_height or intr.width * intr.height > limits.max_pixels:
        raise ProtocolError("too_large", f"hello.intrinsics: {intr.width}x{intr.height} exceeds this server's limits "
                                         f"({limits.max_width}x{limits.max_height}, {limits.max_pixels} pixels)")
    return intr


def resolve_mesh(name: str, meshes: Path | None, where: str) -> str:
    """The path of the mesh an object names: a file name in the server's mesh folder (`photoreg serve --meshes`),
    never a path, so that a client reaches no other file."""
    if meshes is None:
        raise ProtocolError("bad_field", f"{where}: this server has no mesh folder (photoreg serve --meshes DIR), "
                                         "so it inserts no objects")
    if Path(name).name != name or name.startswith(".") or "\\" in name:
        raise ProtocolError("bad_field", f"{where}: a mesh is named by its file name in the server's mesh folder, "
                                         f"got {name!r:.80}")
    path = Path(meshes) / name
    try:
        found = path.is_file()
    except OSError:   # a name too long for the file system: no such mesh (the folder is not the client's to see)
        found = False
    if not found:
        known = sorted(p.name for p in Path(meshes).iterdir()
                       if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in MESH_SUFFIXES)
        raise ProtocolError("bad_field", f"{where}: no mesh {name!r:.80} on this server (it has: "
                                         f"{', '.join(known[:20]) or 'none'}{', ...' if len(known) > 20 else ''})")
    return str(path)


def session_from_options(value, device: str, limits: Limits, meshes: Path | None = None) -> tuple[Session, list[str]]:
    """Session from hello.options, keyed like a session file: {lighting: {...}, reconstruction: {...},
    render: {shadows}, objects: [...], track: bool}; objects name their mesh in `meshes` (resolve_mesh).
    Returns the session and notes for `ready`."""
    opts = _object(value, "hello.options")
    unknown = sorted(set(opts) - {"lighting", "reconstruction", "render", "objects", "track"})
    if unknown:
        raise ProtocolError("bad_field", f"hello.options: unknown field(s) {', '.join(unknown)} "
                                         "(known: lighting, objects, reconstruction, render, track)")
    s = Session(device=device, source="hello.options")
    notes: list[str] = []
    try:
        if "lighting" in opts:
            s.lighting = _fill(LightingConfig, opts["lighting"], "hello.options", "lighting")
        if "reconstruction" in opts:
            recon = _object(opts["reconstruction"], "hello.options.reconstruction")
            refused = sorted(set(recon) - set(CLIENT_RECONSTRUCTION_KEYS))
            if refused:
                raise ProtocolError("bad_field", f"hello.options.reconstruction: field(s) {', '.join(refused)} "
                                                 f"cannot be set by a client (allowed: "
                                                 f"{', '.join(CLIENT_RECONSTRUCTION_KEYS)})")
            s.reconstruction = _fill(ReconstructionConfig, recon, "hello.options", "reconstruction")
        if "render" in opts:
            s.render = _fill(RenderConfig, opts["render"], "hello.options", "render")
        if "objects" in opts:
            objs = opts["objects"]
            if not isinstance(objs, list):
                raise ProtocolError("bad_field", f"hello.options.objects must be a list, got {type(objs).__name__}")
            if len(objs) > limits.max_objects:   # a server limit, as the others below
                raise ProtocolError("too_large", f"hello.options.objects: {len(objs)} objects, this server takes at "
                                                 f"most {limits.max_objects}")
            s.objects = [_fill(ObjectConfig, o, "hello.options", f"objects[{i}]") for i, o in enumerate(objs)]
            for i, o in enumerate(s.objects):   # their values are validate's (below), their meshes the server's
                o.mesh = resolve_mesh(o.mesh, meshes, f"hello.options.objects[{i}].mesh")
        if "track" in opts:
            if not isinstance(opts["track"], bool):
                raise ProtocolError("bad_field",
                                    f"hello.options.track must be true or false, got {opts['track']!r:.80}")
            s.recording.use_poses = not opts["track"]
        validate(s)
    except ProtocolError:
        raise
    except ValueError as e:
        raise ProtocolError("bad_field", str(e)) from None
    L, R = s.lighting, s.reconstruction
    for ok, msg in ((L.rays <= limits.max_rays, f"lighting.rays must be <= {limits.max_rays} on this server"),
                    (L.stride <= limits.max_stride, f"lighting.stride must be <= {limits.max_stride} on this server"),
                    (R.voxel_size >= limits.min_voxel_size,
                     f"reconstruction.voxel_size must be >= {limits.min_voxel_size} m on this server"),
                    (R.trunc_voxels <= limits.max_trunc_voxels,
                     f"reconstruction.trunc_voxels must be <= {limits.max_trunc_voxels} on this server"),
                    (R.depth_max <= limits.max_depth,
                     f"reconstruction.depth_max must be <= {limits.max_depth} m on this server"),
                    (L.sun_candidates <= limits.max_sun_candidates,
                     f"lighting.sun_candidates must be <= {limits.max_sun_candidates} on this server"),
                    *((v <= limits.max_light_rays, f"{k} must be <= {limits.max_light_rays} on this server")
                      for k, v in (("lighting.sun_rays", L.sun_rays), ("render.light_rays", s.render.light_rays))),
                    *((v <= limits.max_samples, f"lighting.{k} must be <= {limits.max_samples} on this server")
                      for k, v in (("max_samples", L.max_samples), ("sun_samples", L.sun_samples),
                                   ("history", L.history)))):
        if not ok:
            raise ProtocolError("too_large", f"hello.options: {msg}")
    return s, notes


def parse_hello(header: dict, device: str, limits: Limits, meshes: Path | None = None) -> Hello:
    """Validate a `hello` (version first, so a client of another major version learns that first); objects name
    meshes in `meshes` (the server's mesh folder)."""
    version = check_version(_get(header, "version", "hello"))
    intr = parse_intrinsics(_get(header, "intrinsics", "hello"), limits)
    session, notes = session_from_options(header.get("options", {}), device, limits, meshes)
    token = header.get("token")
    if token is not None and not isinstance(token, str):
        raise ProtocolError("bad_field", "hello.token must be a string")
    composite = header.get("composite", COMPOSITE_ENCODINGS[0])
    if composite not in COMPOSITE_ENCODINGS:
        raise ProtocolError("bad_field", f"hello.composite must be one of {', '.join(COMPOSITE_ENCODINGS)}, "
                                         f"got {composite!r:.80}")
    return Hello(version, intr, session, token, notes, composite)


def _png_size(data: bytes) -> tuple[int, int]:
    if len(data) < 24 or data[:8] != _PNG_MAGIC or data[12:16] != b"IHDR":
        raise ValueError("not a PNG image")
    return struct.unpack(">II", data[16:24])


def _jpeg_size(data: bytes) -> tuple[int, int]:
    """(width, height) from the first start-of-frame marker, without decoding the image."""
    if data[:2] != b"\xff\xd8":
        raise ValueError("not a JPEG image")
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            raise ValueError("corrupt JPEG marker structure")
        marker = data[i + 1]
        if marker == 0xFF:          # fill bytes: to the last of them
            i = after_fill(data, i) - 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            i += 2
            continue
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 9 > len(data):
                break
            h, w = struct.unpack(">HH", data[i + 5:i + 9])
            return w, h
        if marker in (0xD9, 0xDA):  # end of image / start of scan before any frame header
            break
        i += 2 + struct.unpack(">H", data[i + 2:i + 4])[0]
    raise ValueError("no JPEG frame header found")


def _payload(spec, name: str, payload: memoryview, encodings: tuple[str, ...],
             message: str = "frame") -> tuple[str, bytes]:
    where = f"{message}.{name}"
    obj = _object(spec, where)
    enc = _get(obj, "encoding", where)
    if enc not in encodings:
        raise ProtocolError("bad_field", f"{where}.encoding must be one of {', '.join(encodings)}, got {enc!r:.80}")
    off = _count(_get(obj, "offset", where), f"{where}.offset")
    n = _count(_get(obj, "length", where), f"{where}.length")
    if off + n > len(payload):
        raise ProtocolError("bad_field", f"{where}: bytes {off}..{off + n} lie outside the {len(payload)}-byte payload")
    return enc, bytes(payload[off:off + n])


def _decode_color(enc: str, data: bytes, intr: Intrinsics) -> np.ndarray:
    w, h = intr.width, intr.height
    if enc == "rgb8":
        if len(data) != w * h * 3:
            raise ProtocolError("bad_field", f"frame.color: rgb8 needs {w}x{h}x3 = {w * h * 3} bytes, got {len(data)}")
        return np.frombuffer(data, np.uint8).reshape(h, w, 3).copy()
    try:
        size = _png_size(data) if enc == "png" else _jpeg_size(data)
    except (ValueError, struct.error) as e:
        raise ProtocolError("bad_image", f"frame.color: {e}") from None
    if size != (w, h):
        raise ProtocolError("bad_image", f"frame.color: image is {size[0]}x{size[1]}, the intrinsics say {w}x{h}")
    img = None if jpeg_cut_short(data) else cv2.imdecode(np.frombuffer(data, np.uint8), COLOR_FLAGS)
    if img is None or img.shape[:2] != (h, w):
        raise ProtocolError("bad_image", f"frame.color: corrupt {enc} data")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _depth_size(spec: dict, intr: Intrinsics) -> tuple[int, int]:
    """frame.depth's optional width and height (default the intrinsics'): at most the colour's, its shape."""
    w, h = (_count(spec.get(k, v), f"frame.depth.{k}") for k, v in (("width", intr.width), ("height", intr.height)))
    if not (0 < w <= intr.width and 0 < h <= intr.height):
        raise ProtocolError("bad_field", f"frame.depth: {w}x{h} must be at least 1x1 and at most the colour's "
                                         f"{intr.width}x{intr.height}")
    return w, h


def _decode_depth(enc: str, data: bytes, intr: Intrinsics, w: int, h: int) -> np.ndarray:
    """Depth in metres at the colour's size from a w x h depth image registered to it (io.images.registered_depth)."""
    raw = _decode_raw_depth(enc, data, intr, w, h)
    try:
        return registered_depth(raw, intr.width, intr.height, "frame.depth")
    except ValueError as e:
        raise ProtocolError("bad_field", str(e)) from None


def _decode_raw_depth(enc: str, data: bytes, intr: Intrinsics, w: int, h: int) -> np.ndarray:
    scale = np.float32(intr.depth_scale)
    if enc == "f32":
        if len(data) != w * h * 4:
            raise ProtocolError("bad_field", f"frame.depth: f32 needs {w}x{h}x4 = {w * h * 4} bytes, got {len(data)}")
        return np.frombuffer(data, "<f4").reshape(h, w).astype(np.float32)
    if enc == "u16":
        if len(data) != w * h * 2:
            raise ProtocolError("bad_field", f"frame.depth: u16 needs {w}x{h}x2 = {w * h * 2} bytes, got {len(data)}")
        raw = np.frombuffer(data, "<u2").reshape(h, w)
    else:
        try:
            size = _png_size(data)
        except (ValueError, struct.error) as e:
            raise ProtocolError("bad_image", f"frame.depth: {e}") from None
        if size != (w, h):
            raise ProtocolError("bad_image", f"frame.depth: image is {size[0]}x{size[1]}, the frame says {w}x{h}")
        raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.shape != (h, w) or raw.dtype != np.uint16:
            what = "corrupt png data" if raw is None else f"{raw.dtype} with shape {raw.shape}"
            raise ProtocolError("bad_image", f"frame.depth: expected a 16-bit single-channel PNG, got {what}")
    return raw.astype(np.float32) / scale


def decode_frame(header: dict, payload: memoryview, intr: Intrinsics, default_index: int) -> Frame:
    """A Frame from a binary `frame` message; errors carry the frame index when it is known."""
    index = _count(header.get("index", default_index), "frame.index")
    try:
        timestamp = _number(_get(header, "timestamp", "frame"), "frame.timestamp")
        shutter = header.get("shutter")
        if shutter is not None and not 0 <= _number(shutter, "frame.shutter") <= 1:
            raise ProtocolError("bad_field", f"frame.shutter must be seconds in 0..1, got {shutter!r:.80}")
        pose = header.get("pose")
        if pose is not None:
            try:
                arr = np.array(pose, dtype=np.float64)
            except (ValueError, TypeError, OverflowError):
                raise ProtocolError("bad_field", "frame.pose must be a 4x4 array of numbers or null") from None
            try:
                pose = check_pose(arr, "frame.pose")
            except ValueError as e:
                raise ProtocolError("bad_field", str(e)) from None
        cenc, cdata = _payload(_get(header, "color", "frame"), "color", payload, COLOR_ENCODINGS)
        dspec = _get(header, "depth", "frame")
        denc, ddata = _payload(dspec, "depth", payload, DEPTH_ENCODINGS)
        color = _decode_color(cenc, cdata, intr)
        depth = _decode_depth(denc, ddata, intr, *_depth_size(dspec, intr))
    except ProtocolError as e:
        e.frame = index
        raise
    return Frame(index=index, timestamp=timestamp, color=color, depth=depth, intrinsics=intr, pose=pose,
                 source=f"frame message {index}", shutter=None if shutter is None else float(shutter))

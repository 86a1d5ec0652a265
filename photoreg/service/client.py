"""Client of `photoreg serve` (protocol 1.2, docs/protocol.md) and `photoreg stream`.

`connect()` opens a session (hello -> ready) over websockets' synchronous client; `send_frame()`
returns at once and replies arrive in order through `recv()` / `poll()`, so a plain loop can keep
several frames in flight. `replay()` streams a recording's frames through a client and collects the
lighting records (and the composites of a session with objects); `photoreg stream` saves them like
`photoreg run` (OUT/lighting.jsonl, summary.json, composite/).
"""
from __future__ import annotations

import json
import logging
import os
import signal
import sys
import threading
import time
from collections import OrderedDict
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI
from websockets.protocol import State
from websockets.sync.client import ClientConnection
from websockets.sync.client import connect as ws_connect

from ..io.ahead import Ahead
from ..io.atomic import atomic_path, check_output_dir, hold_folder, write_json
from ..runner import Progress, StageTimes, against_recorded, clear_earlier, writer_threads
from ..types import Frame, Intrinsics
from .protocol import (CLIENT_RECONSTRUCTION_KEYS, ProtocolError, decode, decode_composite, encode, encode_frame,
                       hello_message, record_from_lighting, token_option)


# The connection's own log: websockets logs a stalled server's missed keepalive ping as a traceback; the client
# reports the connection's end itself (ServiceClosed), so only its critical records would be worth printing.
QUIET = logging.getLogger("photoreg.stream.websocket")
QUIET.setLevel(logging.CRITICAL)
KEEPALIVE_S = 20.0   # a ping this often, and the connection ends when one is not answered within as long


class ServiceClosed(RuntimeError):
    """The server closed the connection (code and reason as the server gave them)."""

    def __init__(self, code: int | None, reason: str):
        super().__init__(f"the server closed the connection (code {code}{': ' + reason if reason else ''})")
        self.code, self.reason = code, reason


class NoReply(RuntimeError):
    """The server answered none of the frames in flight within the reply timeout."""


class Client:
    """A ready session on a photoreg server; use connect() to make one."""

    def __init__(self, ws: ClientConnection, ready: dict):
        self.ws, self.ready = ws, ready

    def send_frame(self, frame: Frame, index: int | None = None, color: str = "png", depth: str = "png16") -> int:
        """Send one frame (encodings as in protocol.encode_frame); returns the index its replies carry."""
        index = frame.index if index is None else index
        self.send_message(encode_frame(frame, index, color, depth))
        return index

    def send_message(self, message: bytes) -> None:
        """Send a message already encoded (a frame's: protocol.encode_frame)."""
        try:
            self.ws.send(message)
        except ConnectionClosed as e:
            raise self._closed(e) from None

    def recv(self, timeout: float | None = None) -> dict | None:
        """Next reply (lighting, composite, error, bye, ...), or None when none came within `timeout` seconds. A
        binary reply (composite) carries its payload bytes under "payload" (protocol.decode_composite reads it)."""
        try:
            data = self.ws.recv(timeout)
        except TimeoutError:
            if self.ws.protocol.state is not State.CLOSED:
                return None
            # ended: websockets marks the state closed a moment before it closes its queue; once it has, the
            # queue gives what is left in it, then ConnectionClosed
            self.ws.recv_events_thread.join()
            return self.recv(0)
        except ConnectionClosed as e:
            raise self._closed(e) from None
        header, payload = decode(data)
        if len(payload):
            header["payload"] = bytes(payload)
        return header

    def poll(self) -> list[dict]:
        """Every reply that has already arrived, without waiting; where the connection has closed meanwhile, those
        read before its end (the next call raises ServiceClosed)."""
        replies = []
        try:
            while (msg := self.recv(0)) is not None:
                replies.append(msg)
        except ServiceClosed:
            if not replies:
                raise
        return replies

    def finish(self, timeout: float = 60.0) -> list[dict]:
        """Say bye; returns the replies still to come, ending with the server's bye, then closes. Where the server
        closed first (its shutdown), the replies it sent before, its bye among them."""
        replies: list[dict] = []
        try:
            self.ws.send(encode({"type": "bye"}))
        except ConnectionClosed:
            pass   # what the server sent before it closed is still read below
        try:
            deadline = time.monotonic() + timeout
            while (left := deadline - time.monotonic()) > 0:
                msg = self.recv(left)
                if msg is None:
                    break
                replies.append(msg)
                if msg["type"] == "bye":
                    break
        except (ConnectionClosed, ServiceClosed):
            pass
        self.close()
        return replies

    def close(self) -> None:
        self.ws.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _closed(self, e: ConnectionClosed) -> ServiceClosed:
        rcvd, sent = e.rcvd, e.sent
        if rcvd is None and sent is not None and sent.reason == "keepalive ping timeout":
            return ServiceClosed(None, f"no close frame: the server answered no keepalive ping within "
                                       f"{self.ws.ping_timeout:g} s")
        return ServiceClosed(rcvd.code if rcvd else None, rcvd.reason if rcvd else "no close frame")


def connect(url: str, intrinsics: Intrinsics, options: dict | None = None, token: str | None = None,
            timeout: float = 60.0, composite: str | None = None) -> Client:
    """Open a session: hello with the camera and options (keyed like a session file: lighting,
    reconstruction, render, objects, track) and the composites' encoding (jpeg or png; the server's default
    jpeg when None), wait for ready. An error reply raises ProtocolError."""
    try:
        # Entered, not called: the way to keep a connection across websockets versions; Client.close() closes it.
        ws = ws_connect(url, open_timeout=timeout, max_size=64 * 2**20, compression=None, close_timeout=5,
                        ping_interval=KEEPALIVE_S, ping_timeout=KEEPALIVE_S, logger=QUIET).__enter__()
    except (OSError, InvalidURI, InvalidHandshake, TimeoutError) as e:
        raise RuntimeError(f"{url}: cannot connect to a photoreg server ({e})") from None
    client = Client(ws, {})
    try:
        try:
            ws.send(encode(hello_message(intrinsics, options, token, composite)))
        except ConnectionClosed:   # refused at once (too_many_clients, shutting_down): its error and close came first
            pass                   # and are what recv gives (before: a raw ConnectionClosed traceback)
        reply = client.recv(timeout)
    except Exception:
        client.close()
        raise
    if reply is None or reply["type"] != "ready":
        client.close()
        if reply is None:
            raise RuntimeError(f"{url}: no reply to hello within {timeout:g} s")
        if reply["type"] == "error":
            raise ProtocolError(reply.get("code", "internal"), reply.get("message", ""))
        raise RuntimeError(f"{url}: expected ready, got {reply['type']!r}")
    client.ready = reply
    return client


def percentiles(values_ms: list[float]) -> dict:
    """p50/p95/p99/mean/max of latencies in ms (None when there are none)."""
    if not values_ms:
        return {"p50": None, "p95": None, "p99": None, "mean": None, "max": None}
    v = np.asarray(values_ms)
    return {"p50": round(float(np.percentile(v, 50)), 3), "p95": round(float(np.percentile(v, 95)), 3),
            "p99": round(float(np.percentile(v, 99)), 3), "mean": round(float(v.mean()), 3),
            "max": round(float(v.max()), 3)}


def encoded_ahead(frames: Iterable[Frame], color: str, depth: str, threads: int) -> Ahead[Frame, tuple[Frame, bytes]]:
    """(frame, its frame message, protocol.encode_frame) in order, encoded on `threads` threads up to 2 * threads
    frames ahead of the caller (a TUM frame's lossless colour and depth PNGs took 23-42 ms, more than the server's
    whole frame on a GPU)."""
    return Ahead(lambda frame: (frame, encode_frame(frame, None, color, depth)), frames, threads, 2 * threads,
                 name="photoreg-encode")


def replay(client: Client, frames: Iterable[Frame], realtime: bool = False, window: int = 2,
           color: str = "png", depth: str = "png16", on_record: Callable[[dict], None] | None = None,
           reply_timeout: float = 120.0, on_composite: Callable[[int, str, bytes], None] | None = None,
           threads: int = 1) -> dict:
    """Stream frames through a session and collect the replies; returns the figures of summary.json.

    Without `realtime`, at most `window` frames are in flight (nothing is dropped when window <= the
    server's queue); with it, frames go out at their recording timestamps and the server drops what
    it cannot keep up with. A frame whose reply never comes (dropped) is known when a later frame's
    reply arrives, replies being in order. Ctrl-C (KeyboardInterrupt), the server's bye or its closing
    the connection stop the sending; what has arrived is kept and `stopped` says why. A composite (sessions
    with objects) goes to on_composite(frame index, encoding, image bytes). The frames are encoded on `threads`
    threads ahead of the sending (encoded_ahead).
    """
    pending: OrderedDict[int, float] = OrderedDict()   # index -> send time, in send order
    latencies, server_latencies, weak, errors = [], [], [], []
    counts = {"sent": 0, "dropped": 0, "composites": 0}
    stage_ms = StageTimes()   # records go to on_record, not kept (5 KB a frame)
    bye: dict = {}
    t_start = time.perf_counter()
    ts0 = None

    def handle(msg: dict) -> None:
        now = time.perf_counter()
        if msg["type"] == "lighting":
            index = msg["frame"]
            while pending and next(iter(pending)) != index:   # older frames without a reply were dropped
                pending.popitem(last=False)
                counts["dropped"] += 1
            if pending:
                latencies.append((now - pending.pop(index)) * 1000.0)
            server_latencies.append(msg["latency_ms"])
            record = record_from_lighting(msg)
            stage_ms.add(record["timings_ms"])
            if record["diagnostics"].get("weak"):
                weak.append(record["frame"])
            if on_record is not None:
                on_record(record)
        elif msg["type"] == "composite":
            counts["composites"] += 1
            if on_composite is not None:
                on_composite(*decode_composite(msg, memoryview(msg.get("payload", b""))))
        elif msg["type"] == "error":
            pending.pop(msg.get("frame"), None)
            errors.append({k: msg.get(k) for k in ("frame", "code", "message")})
        elif msg["type"] == "bye":
            bye.update(msg)

    stopped = None   # why sending stopped early
    messages = encoded_ahead(frames, color, depth, threads)
    try:
        for frame, message in messages:
            if realtime:
                ts0 = frame.timestamp if ts0 is None else ts0
                due = t_start + (frame.timestamp - ts0)
                while (left := due - time.perf_counter()) > 0 and not bye:
                    if (msg := client.recv(left)) is not None:
                        handle(msg)
            else:
                while len(pending) >= window and not bye:
                    msg = client.recv(reply_timeout)
                    if msg is None:   # a server that stopped answering: what arrived is kept, as when it closes
                        raise NoReply(f"no reply from the server within {reply_timeout:g} s")
                    handle(msg)
            for msg in client.poll():
                handle(msg)
            if bye:
                stopped = f"the server said bye: {bye.get('reason')}"
                break
            client.send_message(message)
            pending[frame.index] = time.perf_counter()
            counts["sent"] += 1
    except KeyboardInterrupt:
        stopped = "interrupted"
    except (ServiceClosed, NoReply) as e:
        stopped = str(e)
    finally:
        messages.close()
    if not bye:
        for msg in client.finish(timeout=10.0 if stopped else reply_timeout):
            handle(msg)
    client.close()
    counts["dropped"] += len(pending)   # never answered: dropped or cancelled at the end
    wall = time.perf_counter() - t_start
    n = stage_ms.frames
    return {
        "device": client.ready.get("device"), "frames_sent": counts["sent"], "frames_processed": n,
        "composites": counts["composites"],
        "frames_dropped": counts["dropped"], "errors": errors, "stopped": stopped,
        "wall_s": round(wall, 3), "frames_per_s": round(n / wall, 3) if wall > 0 else None,
        "latency_ms": percentiles(latencies), "server_latency_ms": percentiles(server_latencies),
        "weak_frames": weak, "timings_ms_mean": stage_ms.means(),
        "server_bye": bye, "settings": client.ready.get("settings"),
    }


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def session_options(session) -> dict:
    """hello.options that ask a server for what `photoreg run SESSION` does: the session's (a file's path, or one
    loaded) [lighting] and [render], the [reconstruction] keys a client may set and its [[objects]], each naming
    its mesh by file name (the server looks it up in its --meshes folder)."""
    from ..config import Session, load_session

    # the server has the meshes; the recording is the command's
    s = session if isinstance(session, Session) else load_session(session, files=False)
    options = {"lighting": dict(vars(s.lighting)), "render": dict(vars(s.render)),
               "reconstruction": {k: getattr(s.reconstruction, k) for k in CLIENT_RECONSTRUCTION_KEYS}}
    if s.objects:
        options["objects"] = [{"mesh": Path(o.mesh).name, "position": list(o.position), "rotation": list(o.rotation),
                               "scale": o.scale, "albedo": o.albedo if isinstance(o.albedo, str) else list(o.albedo),
                               "smooth": o.smooth} for o in s.objects]
    if not s.recording.use_poses:
        options["track"] = True
    return options


def stream_command(args) -> int:
    """`photoreg stream RECORDING --url URL`: replay a recording through a server, save the replies."""
    from ..config import Session, check_pose_time_offset, load_session, select_frames
    from ..io.recording import open_recording

    # RECORDING opened as `photoreg run SESSION` opens the session's: its format, undistortion, pose offset, frames
    session = load_session(args.session, files=False) if args.session else Session()
    offset = session.recording.pose_time_offset if args.pose_time_offset is None else args.pose_time_offset
    check_pose_time_offset(offset, "--pose-time-offset")
    rec = open_recording(args.recording, fmt=session.recording.format, undistort=session.recording.undistort,
                         pose_time_offset=offset)
    indices = select_frames(args.frames or session.frames, len(rec), args.recording)
    options: dict = session_options(session) if args.session else {}
    lighting = {k: v for k, v in (("bands", args.bands), ("rays", args.rays), ("stride", args.stride),
                                  ("ray_length", args.ray_length), ("every", args.every),
                                  ("asynchronous", args.asynchronous or None)) if v is not None}
    if lighting:
        options["lighting"] = {**options.get("lighting", {}), **lighting}
    if args.voxel_size is not None:
        options["reconstruction"] = {**options.get("reconstruction", {}), "voxel_size": args.voxel_size}
    if args.render_stride is not None:
        options["render"] = {**options.get("render", {}), "stride": args.render_stride}
    if args.no_poses or not rec.has_poses:
        options["track"] = True
    if args.window < 1:
        raise ValueError(f"--window must be >= 1 (frames in flight), got {args.window}")
    out = Path(args.out) if args.out else None
    lock = None
    if out is not None:   # held while the stream writes there: another run or stream into it is refused
        check_output_dir(out, "--out")
        out.mkdir(parents=True, exist_ok=True)
        lock = hold_folder(out, "--out")
    try:
        return _stream(args, rec, indices, options, out)
    finally:
        if lock is not None:
            os.close(lock)


def _stream(args, rec, indices: list[int], options: dict, out: Path | None) -> int:
    """stream_command's replay, into the output folder `out` it holds (None: no files)."""
    from ..io.poses import write_tum_trajectory
    from ..io.recording import ReadAhead
    from ..recon.tracking import MAX_LISTED, ate_against

    skipped: list[dict] = []
    progress = Progress(len(indices), args.quiet)
    t_hello = time.perf_counter()
    client = connect(args.url, rec.intrinsics, options, token_option(args.token),
                     composite=args.composite)
    hello_ms = round((time.perf_counter() - t_hello) * 1000.0, 1)   # connect, hello, ready
    frames = ReadAhead(rec, indices, on_error=lambda i, msg: skipped.append({"frame": i, "error": msg}),
                       threads=writer_threads())
    partial = None if out is None else open(out / "lighting.jsonl.partial", "w")

    tracked: dict[int, tuple[float, np.ndarray]] = {}   # frame -> (timestamp, pose) the server tracked (`track`)
    untracked: list[dict] = []   # the frames its tracking failed, each {"frame", "reason"} (from the reply's notes)
    unconfirmed: list[int] = []  # the frames it tracked unconfirmed

    cleared = False   # a frame answered: the folder is this stream's (clear_earlier)

    def on_record(record: dict) -> None:
        nonlocal cleared
        if partial is not None:
            if not cleared:
                clear_earlier(out, {"composite": (".png", ".jpg")},
                              ("lighting.jsonl", "summary.json", "trajectory.txt"))
                cleared = True
            partial.write(json.dumps(record) + "\n")
            partial.flush()
        if options.get("track"):
            said = [n.split(": ", 1)[1] for n in record["diagnostics"].get("notes", [])
                    if n.startswith(f"frame {record['frame']}: tracking ")]
            if record.get("pose") is not None:
                tracked[record["frame"]] = (record["timestamp"], np.asarray(record["pose"], dtype=np.float64))
                if any(n.startswith("tracking unconfirmed") for n in said):
                    unconfirmed.append(record["frame"])
            else:
                untracked.append({"frame": record["frame"], "reason": said[0] if said else "no pose"})
        progress.step(f"frame {record['frame']}" + (" (weak)" if record["diagnostics"].get("weak") else ""))

    def on_composite(index: int, encoding: str, image: bytes) -> None:
        if out is not None:
            name = f"{index:06d}.{'png' if encoding == 'png' else 'jpg'}"
            with atomic_path(out / "composite" / name) as tmp:
                tmp.write_bytes(image)

    main_thread = threading.current_thread() is threading.main_thread()
    if main_thread:   # SIGTERM stops like Ctrl-C: what has arrived is saved
        previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        summary = replay(client, frames, realtime=args.realtime, window=args.window, color=args.color,
                         depth=args.depth, on_record=on_record, on_composite=on_composite, threads=writer_threads())
    finally:
        frames.close()
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
        progress.close()
        if partial is not None:
            partial.close()
    summary = {"recording": str(rec.path), "url": args.url, "hello_ms": hello_ms, **summary, "frames_skipped": skipped}
    if options.get("track"):   # as `photoreg run --no-poses` reports it, from the replies
        summary["tracking"] = {"frames": summary["frames_processed"], "failures": untracked[:MAX_LISTED],
                               "unconfirmed": len(unconfirmed), "unconfirmed_frames": unconfirmed[:MAX_LISTED]}
        if len(untracked) > MAX_LISTED:
            summary["tracking"]["failures_not_listed"] = len(untracked) - MAX_LISTED
        if rec.has_poses:
            summary["tracking"].update(ate_against({i: T for i, (_, T) in tracked.items()}, rec.poses))
    if out is not None and not summary["frames_processed"]:   # an earlier stream's outputs stand
        (out / "lighting.jsonl.partial").unlink(missing_ok=True)
        first = f" (frame {skipped[0]['frame']}: {skipped[0]['error']})" if skipped else ""
        why = f"; {summary['stopped']}" if summary["stopped"] else ""
        raise ValueError(f"{rec.path}: no frame was answered{first}{why}; nothing in {out} was replaced")
    if out is not None:
        os.replace(out / "lighting.jsonl.partial", out / "lighting.jsonl")
        write_json(out / "summary.json", summary)
        if options.get("track"):
            write_tum_trajectory(out / "trajectory.txt", [tracked[i] for i in sorted(tracked)])
    for sk in skipped:
        print(f"photoreg: skipped frame {sk['frame']}: {sk['error']}", file=sys.stderr)
    for e in summary["errors"]:
        print(f"photoreg: server error{' on frame ' + str(e['frame']) if e['frame'] is not None else ''}: "
              f"{e['code']}: {e['message']}", file=sys.stderr)
    lat, srv = summary["latency_ms"], summary["server_latency_ms"]
    print(f"{summary['frames_processed']}/{summary['frames_sent']} frames answered on {summary['device']} at "
          f"{summary['frames_per_s']} frames/s; {summary['frames_dropped']} dropped, {len(summary['errors'])} errors"
          + (f" (stopped early: {summary['stopped']})" if summary["stopped"] else ""))
    if lat["p50"] is not None:
        print(f"latency ms (send to reply): p50 {lat['p50']:.1f}  p95 {lat['p95']:.1f}  p99 {lat['p99']:.1f}; "
              f"server side p50 {srv['p50']:.1f}  p95 {srv['p95']:.1f}")
    if "tracking" in summary:
        t = summary["tracking"]
        print(f"tracked {len(tracked)} of the {t['frames']} frames answered{against_recorded(t)}")
    if out is not None:
        print(f"outputs in {out}: lighting.jsonl, summary.json" + (", composite/" if summary["composites"] else "")
              + (", trajectory.txt" if "tracking" in summary else ""))
    return 0 if summary["stopped"] is None else 130 if summary["stopped"] == "interrupted" else 1

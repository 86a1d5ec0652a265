"""`photoreg serve`: the WebSocket service (protocol 1.2, docs/protocol.md), one pipeline per connection.

A connection runs three tasks on the event loop: a reader (receive, validate, start decoding a frame's
images on a helper thread), an orderer (queue the decoded frames in the order they came) and a worker (run
the pipeline in the connection's own process, or with ServerConfig.processes off on its own thread:
photoreg.service.host; reply). The queue between them is bounded and, when a frame arrives while it is full,
drops the oldest waiting frame ('latest wins'), so a client faster than the pipeline gets fresh answers and
memory stays bounded: per connection at most `queue` decoded frames waiting, HANDED in the pipeline, one
composite being encoded, DECODING messages being decoded or decoded and waiting for an earlier one, and websockets'
small receive buffer. A client that does not read its replies stalls only its own worker (a send waits for its
socket; websockets' keepalive ends the connection after about a minute without its pongs); every other connection
keeps its own pipeline and queue. A session with objects (their meshes named in the server's mesh folder,
--meshes) gets each frame's composite after its lighting reply.
"""
from __future__ import annotations

import asyncio
import collections
import hmac
import ipaddress
import logging
import math
import signal
import threading
import time
from concurrent.futures import BrokenExecutor, Future
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.frames import CloseCode

from ..device import open3d_message, resolve_device
from ..types import Frame, Intrinsics
from .host import CompositePatch, PipelineHost
from .protocol import (CLIENT_TYPES, Limits, ProtocolError, bye_message, composite_message, decode, decode_frame,
                       encode, encode_composite, error_message, lighting_message, parse_hello, ready_message,
                       token_option)

log = logging.getLogger("photoreg.serve")
COUNTS = ("received", "processed", "dropped", "cancelled", "errors")   # frames, per connection and in total
SEND_TIMEOUT = 2.0   # s: the last words (bye, errors before closing) to a client that may not be reading
HANDED = 2           # frames a connection's pipeline holds: the one it runs and the next (Connection._feed)
DECODING = 2         # frames a connection decodes at once (a 640x480 frame's two PNGs: 18-20 ms on one core)


@dataclass
class ServerConfig:
    host: str = "127.0.0.1"
    port: int = 8765              # 0: any free port (see PhotoregServer.port)
    token: str | None = None      # clients must send it in hello
    device: str = "auto"
    max_clients: int = 4
    queue: int = 2                # frames waiting per connection before the oldest is dropped
    idle_timeout: float = 300.0   # s without a message (and no frame in work) before closing; <= 0: never
    shutdown_timeout: float = 10.0  # s to finish in-flight frames on shutdown
    hello_timeout: float = 10.0   # s a connection has for its hello where a token is required: one without holds no
                                  # client slot longer (any message, a ping, kept it open until the idle timeout)
    block_count: int = 4000       # initial TSDF hash capacity per session (32 KB per block, grows when full):
                                  # the memory a connection costs, so the server's to choose, not the client's
    limits: Limits = field(default_factory=Limits)
    meshes: str | None = None     # folder of the meshes that clients' objects name (None: no objects)
    processes: bool = True        # each connection's pipeline in a process of its own, else a thread of the server's
                                  # (photoreg.service.host)

    def __post_init__(self) -> None:
        if self.max_clients < 1 or self.queue < 1:
            raise ValueError(f"--max-clients and --queue must be >= 1, got {self.max_clients} and {self.queue}")
        if not 0 <= self.port <= 65535:
            raise ValueError(f"--port must be in 0..65535, got {self.port}")
        if not math.isfinite(self.idle_timeout):
            raise ValueError(f"--idle-timeout must be a number of seconds, got {self.idle_timeout}")
        if self.limits.max_message_bytes < 1024:
            raise ValueError(f"--max-message-mb must allow at least 1 KiB, got {self.limits.max_message_bytes} bytes")
        if self.meshes is not None and not Path(self.meshes).is_dir():
            raise ValueError(f"--meshes {self.meshes}: not a folder")


@dataclass
class _Queued:
    frame: Frame
    received: float   # time.perf_counter() when the message arrived


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


async def last_words(ws: ServerConnection, msg: dict, code: int, reason: str) -> None:
    """A final message, then the closing handshake; never waits long on a client that does not read."""
    try:
        await asyncio.wait_for(ws.send(encode(msg)), SEND_TIMEOUT)
        await ws.close(code, reason)
    except (ConnectionClosed, TimeoutError):
        pass


class Connection:
    """One client: its session (after hello), its queue, its pipeline's thread or process."""

    def __init__(self, server: "PhotoregServer", ws: ServerConnection):
        self.server, self.ws, self.cfg = server, ws, server.config
        self.queue: collections.deque[_Queued] = collections.deque(maxlen=self.cfg.queue)
        # the frames handed to the pipeline, in order: (frame, when handed, the future of its reply); at most HANDED
        self.running: collections.deque[tuple[_Queued, float, Future]] = collections.deque()
        # the frames being decoded, in the order they came: (the future of the Frame, when the message arrived)
        self.decoding: asyncio.Queue[tuple[asyncio.Future, float]] = asyncio.Queue()
        self.decode_slots = asyncio.Semaphore(DECODING)
        self.undecoded = 0               # frames received and neither queued nor reported yet
        self.wake = asyncio.Event()      # the queue has work
        self.idle = asyncio.Event()      # nothing decoding, queued or in the pipeline
        self.authorized = False          # a hello with the server's token (if any) came
        self.idle.set()
        self.host: PipelineHost | None = None   # from hello on (a connection that never says hello costs none)
        self.intrinsics: Intrinsics | None = None
        self.composite: str | None = None   # the session's composite encoding (hello.composite)
        self.stop_reason: str | None = None
        self.reader: asyncio.Task | None = None
        self.counts = collections.Counter()  # of COUNTS

    def stop(self, reason: str) -> None:
        """Server shutdown: stop reading; run() finishes the frame in work and says bye."""
        self.stop_reason = reason
        if self.reader is not None:
            self.reader.cancel()

    async def run(self) -> None:
        """Serve until bye, disconnect, idle timeout, refused token or shutdown; then release everything."""
        self.reader = asyncio.create_task(self._read())
        orderer = asyncio.create_task(self._queue_decoded())
        worker = asyncio.create_task(self._work())
        try:
            await asyncio.wait({self.reader})
            ending = "shutdown" if self.reader.cancelled() else self.reader.result()
            if ending == "bye":
                await self._wait_idle(None, worker)
                await last_words(self.ws, bye_message("client said bye", **self.stats()),
                                 CloseCode.NORMAL_CLOSURE, "bye")
            elif ending == "shutdown":
                self.counts["cancelled"] += len(self.queue)
                self.queue.clear()
                await self._wait_idle(self.cfg.shutdown_timeout, worker)
                await last_words(self.ws, bye_message(self.stop_reason, **self.stats()),
                                 CloseCode.GOING_AWAY, self.stop_reason)
            elif ending == "idle":
                await last_words(self.ws, error_message("idle_timeout", f"no message for {self.cfg.idle_timeout:g} "
                                                                        "s: closing the connection"),
                                 CloseCode.NORMAL_CLOSURE, "idle timeout")
            elif ending in ("unauthorized", "no_hello"):
                why = "missing or wrong token" if ending == "unauthorized" else \
                    f"no hello with the token within {self.cfg.hello_timeout:g} s"
                await last_words(self.ws, error_message("unauthorized", why), CloseCode.POLICY_VIOLATION,
                                 "unauthorized")
        finally:
            orderer.cancel()
            worker.cancel()
            self.queue.clear()
            # Hold the client slot until the pipeline's thread or process is free, so that clients that connect
            # and drop cannot pile them up beyond max_clients (bounded by the shutdown timeout when stopping).
            if self.host is not None:
                try:
                    await asyncio.wait_for(asyncio.to_thread(self.host.close),
                                           self.cfg.shutdown_timeout if self.stop_reason else None)
                except TimeoutError:
                    log.warning("%s: pipeline still busy after %.0f s; leaving it", self.peer,
                                self.cfg.shutdown_timeout)

    @property
    def peer(self) -> str:
        addr = self.ws.remote_address
        return f"{addr[0]}:{addr[1]}" if addr else "client"

    def stats(self) -> dict:
        c = self.counts
        return {"frames_received": c["received"], "frames_processed": c["processed"], "dropped": c["dropped"],
                "cancelled": c["cancelled"], "errors": c["errors"]}

    async def _wait_idle(self, timeout: float | None, worker: asyncio.Task) -> None:
        """Until nothing is in work, the timeout passes or the replies' task has ended (a bug in it must not keep the
        connection, its client slot and a shutdown waiting for ever)."""
        idle = asyncio.ensure_future(self.idle.wait())
        done, _ = await asyncio.wait({idle, worker}, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
        idle.cancel()
        if not done:
            log.warning("%s: frame still in work after %.0f s; closing without its reply", self.peer, timeout)
        elif idle not in done and not worker.cancelled() and worker.exception() is not None:
            log.error("%s: the replies ended", self.peer, exc_info=worker.exception())

    async def _send(self, msg: dict) -> None:
        await self.ws.send(encode(msg))

    async def _report(self, e: Exception) -> None:
        """Tell the client what was wrong with one of its messages (a bug here must not take the connection, let
        alone the server, down)."""
        self.counts["errors"] += 1
        if isinstance(e, ProtocolError):
            await self._send(e.to_message())
            return
        log.error("%s: unexpected error handling a message", self.peer, exc_info=e)
        await self._send(error_message("internal", f"server error while handling the message: {e}"))

    def _settle(self) -> None:
        """Mark the connection idle when no frame is decoding, queued or in the pipeline."""
        if not self.undecoded and not self.queue and not self.running:
            self.idle.set()

    # --------------------------------------------------------------------------------------- reader

    async def _read(self) -> str:
        """Handle messages until the connection ends; returns why: bye, closed, idle, unauthorized or shutdown.
        stop() cancels this task; the flag covers a cancellation that asyncio.wait_for swallows when the
        message arrives at the same moment (Python < 3.12)."""
        idle_timeout = self.cfg.idle_timeout if self.cfg.idle_timeout > 0 else None
        hello_by = time.monotonic() + self.cfg.hello_timeout if self.cfg.token is not None else None
        while self.stop_reason is None:
            wait = idle_timeout
            if hello_by is not None and not self.authorized:   # no hello with the token yet: its deadline
                wait = min(max(hello_by - time.monotonic(), 0.0), wait or math.inf)
            try:
                data = await asyncio.wait_for(self.ws.recv(), wait)
            except TimeoutError:
                if hello_by is not None and not self.authorized and time.monotonic() >= hello_by:
                    return "no_hello"
                if not self.idle.is_set():
                    continue  # the client waits for frames still in work: not idle
                return "idle"
            except ConnectionClosed:
                return "closed"
            received = time.perf_counter()
            try:
                header, payload = decode(data)
                kind = header["type"]
                if kind == "hello":
                    if await self._hello(header) == "unauthorized":
                        return "unauthorized"
                elif kind == "frame":
                    await self._frame(header, payload, received)
                elif kind == "bye":
                    return "bye"
                else:
                    raise ProtocolError("unknown_type", f"unknown message type {kind!r:.60}: a client sends "
                                                        f"{', '.join(CLIENT_TYPES)}")
            except ConnectionClosed:
                return "closed"
            except Exception as e:
                try:
                    await self._report(e)
                except ConnectionClosed:
                    return "closed"
        return "shutdown"

    async def _hello(self, header: dict) -> str | None:
        if self.host is not None:
            raise ProtocolError("already_ready", "hello was already accepted on this connection: open a new "
                                                 "connection for another session")
        token = self.cfg.token
        if token is not None:
            given = header.get("token")
            if not isinstance(given, str) or not hmac.compare_digest(given.encode(errors="surrogatepass"),
                                                                     token.encode()):
                log.warning("%s: refused: missing or wrong token", self.peer)
                return "unauthorized"
        self.authorized = True
        hello = parse_hello(header, self.server.device, self.cfg.limits,
                            Path(self.cfg.meshes) if self.cfg.meshes is not None else None)
        hello.session.reconstruction.block_count = self.cfg.block_count
        self.host = self.server.take_host()   # set first: a connection ended meanwhile still releases it
        try:
            await asyncio.wrap_future(self.host.open(hello.session, hello.intrinsics))
        except Exception as e:
            log.exception("%s: could not start a pipeline", self.peer)
            host, self.host = self.host, None
            await asyncio.to_thread(host.close)
            text = open3d_message(e)
            text = text if self.cfg.meshes is None else text.replace(f"{Path(self.cfg.meshes)}/", "")
            raise ProtocolError("pipeline", f"could not start the pipeline: {text}") from None   # no server paths
        try:   # the session is live once the client has its ready
            await self._send(ready_message(hello, self.server.device, self.cfg.queue, self.cfg.limits))
        except Exception:
            host, self.host = self.host, None
            await asyncio.to_thread(host.close)
            raise
        self.host.ready = True
        self.intrinsics, self.composite = hello.intrinsics, hello.composite
        k = hello.intrinsics
        log.info("%s: session started (%dx%d, bands %d, rays %d, stride %d)", self.peer, k.width, k.height,
                 hello.session.lighting.bands, hello.session.lighting.rays, hello.session.lighting.stride)
        return None

    async def _frame(self, header: dict, payload: memoryview, received: float) -> None:
        if self.host is None or not self.host.ready:
            raise ProtocolError("not_ready", "frame before hello: send hello first")
        self.counts["received"] += 1
        # at most DECODING between here and the queue: the next message waits for a slot, which the orderer frees as it
        # takes the frame (freed as decoding ended, fast frames behind a slow one piled up decoded, 28 of 63 MB each)
        await self.decode_slots.acquire()
        self.undecoded += 1
        self.idle.clear()
        decoded = asyncio.ensure_future(asyncio.to_thread(decode_frame, header, payload, self.intrinsics,
                                                          self.counts["received"] - 1))
        self.decoding.put_nowait((decoded, received))

    async def _queue_decoded(self) -> None:
        """Queue the frames in the order they came as their decoding ends (DECODING of them at once on helper
        threads: a connection whose frames took 18-20 ms each to decode got no more than 50-55 replies a second
        while they were decoded one at a time); a frame that does not decode gets its error instead. Frames decoded
        after a shutdown began are cancelled."""
        while True:
            decoded, received = await self.decoding.get()
            try:
                frame = await decoded
            except Exception as e:
                self.decode_slots.release()
                self.undecoded -= 1
                self._settle()
                try:
                    await self._report(e)
                except ConnectionClosed:
                    pass
                continue
            self.decode_slots.release()
            self.undecoded -= 1
            if self.stop_reason is not None:
                self.counts["cancelled"] += 1
                self._settle()
                continue
            if len(self.queue) == self.queue.maxlen:
                self.counts["dropped"] += 1    # the deque drops its oldest entry on append
            self.queue.append(_Queued(frame, received))
            self.wake.set()
            self._feed()

    # --------------------------------------------------------------------------------------- worker

    def _feed(self) -> None:
        """Hand queued frames to the connection's pipeline while it holds fewer than HANDED (the one it runs and the
        next, handed in beside it: a process's hand-over, the frame sent to it and picked up there, took 8-9 ms a
        frame on an H100's host, now off the frames' path). Called by the orderer when a frame is queued and by the
        worker when one is done; both on the event loop."""
        while self.queue and len(self.running) < HANDED:
            item = self.queue.popleft()
            try:
                future = self.host.process(item.frame)
            except BrokenExecutor as e:   # the process died: the worker says so when it comes to this frame
                future = Future()
                future.set_exception(e)
            self.running.append((item, time.perf_counter(), future))

    async def _work(self) -> None:
        """Reply to the frames in the pipeline, in order, as each is done; a done frame's composite (the box of it that
        differs from the frame, host.CompositePatch) is converted to sRGB and encoded on a helper thread while the next
        frame runs (10-20 ms at 640x480). A pipeline process that
        died ends the connection (error, then close code 1011)."""
        try:
            while True:
                self._feed()
                if not self.running:
                    self._settle()
                    self.wake.clear()
                    await self.wake.wait()
                    continue
                item, handed, future = self.running[0]
                index = item.frame.index
                try:
                    record, done, patch = await asyncio.wrap_future(future)
                except BrokenExecutor as e:
                    log.error("%s: the connection's pipeline process stopped at frame %d: %s", self.peer, index, e)
                    self.counts["errors"] += 1
                    await last_words(self.ws, error_message("pipeline", f"frame {index}: the pipeline's process "
                                                                        "stopped (killed, or out of memory?)", index),
                                     CloseCode.INTERNAL_ERROR, "pipeline process stopped")
                    return
                except Exception as e:
                    log.warning("%s: frame %d failed: %s", self.peer, index, e)
                    self.counts["errors"] += 1   # Open3D's words without its colour codes and C++ location
                    await self._send(error_message("pipeline", f"frame {index}: {open3d_message(e)}", index))
                    continue
                finally:
                    self.running.popleft()
                self._feed()   # the next frame goes in before this one's reply
                self.counts["processed"] += 1
                try:
                    await self._send(lighting_message(record, self.counts["dropped"],
                                                      (time.perf_counter() - item.received) * 1000.0,
                                                      (handed - item.received) * 1000.0))
                except ConnectionClosed:
                    raise
                except Exception as e:   # a reply that cannot be made must not end the replies to the next frames
                    log.error("%s: frame %d: no reply", self.peer, index, exc_info=e)
                    self.counts["errors"] += 1
                    await self._send(error_message("internal", f"frame {index}: the reply could not be made: {e}",
                                                   index))
                    continue
                if patch is not None:
                    try:
                        image = await asyncio.to_thread(_encoded, patch, item.frame.color, self.composite)
                    except ValueError as e:
                        self.counts["errors"] += 1
                        await self._send(error_message("pipeline", f"frame {index}: {e}", index))
                        continue
                    await self.ws.send(composite_message(done, image, self.composite))
        except ConnectionClosed:
            pass


def _encoded(patch: CompositePatch, color: np.ndarray, encoding: str) -> bytes:
    """The composite message's image of a frame: its colour with the patch's pixels, encoded."""
    return encode_composite(patch.over(color), encoding)


class PhotoregServer:
    """The WebSocket server: accepts connections up to max_clients, shuts down gracefully."""

    def __init__(self, config: ServerConfig):
        self.config = config
        self.device = ""
        self.connections: dict[Connection, asyncio.Task] = {}
        self.closing = False
        self.totals = collections.Counter()   # over finished connections
        self._ws_server = None
        self._spare: PipelineHost | None = None   # processes: the next connection's, started and warmed ahead
        self._warming = None                       # ... the future of its warm-up

    def _new_spare(self) -> None:
        """Start the next connection's process (ServerConfig.processes) and its device now; best effort: without
        one a connection starts its own at hello."""
        if not self.config.processes or self.closing:
            return
        spare = PipelineHost(True)
        try:
            self._warming = spare.warm(self.device)
            self._spare = spare
        except Exception:  # noqa: BLE001 - e.g. a script that starts the server at import (no __main__ guard)
            log.warning("could not start a spare pipeline process; each connection starts its own", exc_info=True)
            spare.close()

    def take_host(self) -> PipelineHost:
        """A connection's pipeline host at its hello: the spare process unless its start failed (and a new spare
        started), or one of its own."""
        host, self._spare = self._spare, None
        if host is not None and self._warming.done() and self._warming.exception() is not None:
            log.warning("the spare pipeline process failed to start (%s); starting another", self._warming.exception())
            host.close()
            host = None
        if host is None:
            host = PipelineHost(self.config.processes)
        self._new_spare()
        return host

    async def start(self) -> None:
        cfg = self.config
        self.device = resolve_device(cfg.device)   # also initialises Warp once, before any pipeline thread
        if not is_loopback(cfg.host):
            log.warning("listening on %s, reachable from other machines%s", cfg.host,
                        "" if cfg.token else " without a token (set --token or PHOTOREG_TOKEN)")
        self._ws_server = await serve(self._handle, cfg.host, cfg.port, max_size=cfg.limits.max_message_bytes,
                                      max_queue=4, compression=None, close_timeout=SEND_TIMEOUT)
        self._new_spare()

    @property
    def port(self) -> int:
        return self._ws_server.sockets[0].getsockname()[1]

    @property
    def url(self) -> str:
        host = self.config.host
        return f"ws://{f'[{host}]' if ':' in host else host}:{self.port}"

    def stats(self) -> dict:
        """Totals over finished connections plus the live ones (safe to call from another thread)."""
        total = collections.Counter(self.totals)
        for conn in list(self.connections):
            total.update(conn.counts)
        return {"connections": len(self.connections), **{k: total[k] for k in COUNTS}}

    async def _handle(self, ws: ServerConnection) -> None:
        if self.closing or len(self.connections) >= self.config.max_clients:
            error, text, close_code = (("shutting_down", "the server is shutting down", CloseCode.GOING_AWAY)
                                       if self.closing else
                                       ("too_many_clients", f"the server already serves {self.config.max_clients} "
                                                            "client(s): try again later", CloseCode.TRY_AGAIN_LATER))
            await last_words(ws, error_message(error, text), close_code, error)
            return
        conn = Connection(self, ws)
        self.connections[conn] = asyncio.current_task()
        log.info("%s: connected (%d/%d)", conn.peer, len(self.connections), self.config.max_clients)
        try:
            await conn.run()
        finally:
            del self.connections[conn]
            self.totals.update(conn.counts)
            s = conn.stats()
            log.info("%s: closed after %d frames (%d processed, %d dropped, %d errors)", conn.peer,
                     s["frames_received"], s["frames_processed"], s["dropped"], s["errors"])

    async def shutdown(self, reason: str = "server shutting down") -> None:
        """Refuse new clients, finish each connection's frame in work, say bye, close with 1001."""
        self.closing = True
        tasks = list(self.connections.values())
        for conn in list(self.connections):
            conn.stop(reason)
        if tasks:
            await asyncio.wait(tasks, timeout=self.config.shutdown_timeout + 2 * SEND_TIMEOUT + 1)
        # close() gives connections still open 1001 without a reason: its code and reason arguments are newer
        # than the websockets >= 14 that pyproject allows (15.0.1 raised TypeError here; shutdown never finished)
        self._ws_server.close(close_connections=True)
        await self._ws_server.wait_closed()
        if self._spare is not None:
            await asyncio.to_thread(self._spare.close)
            self._spare = None


class ServerThread:
    """A PhotoregServer on its own event loop in a background thread (tests, embedding in sync programs)."""

    def __init__(self, config: ServerConfig):
        self.server = PhotoregServer(config)
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="photoreg-serve", daemon=True)

    def start(self) -> str:
        """Start listening; returns the ws:// URL."""
        self._thread.start()
        asyncio.run_coroutine_threadsafe(self.server.start(), self._loop).result()
        return self.server.url

    def stop(self, reason: str = "server shutting down") -> None:
        try:
            asyncio.run_coroutine_threadsafe(self.server.shutdown(reason), self._loop).result()
        finally:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join()
            self._loop.close()

    def __enter__(self) -> "ServerThread":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


async def serve_until_signal(config: ServerConfig) -> dict:
    """Serve until SIGINT or SIGTERM, then shut down gracefully; returns the server's totals."""
    server = PhotoregServer(config)
    await server.start()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    print(f"photoreg serve: listening on {server.url} (device {server.device}, up to {config.max_clients} clients"
          f"{', a process each' if config.processes else ', threads of this process'}, queue {config.queue}, "
          f"token {'required' if config.token else 'off'})", flush=True)
    await stop.wait()
    log.info("signal received: finishing frames in work and closing connections")
    await server.shutdown()
    return server.stats()


def serve_command(args) -> int:
    """`photoreg serve`: run the service until SIGINT/SIGTERM."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s photoreg serve: %(message)s")
    logging.getLogger("websockets").setLevel(logging.WARNING)   # our own lines say who came and went
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)   # clients' corrupt images get error replies
    if not (math.isfinite(args.max_message_mb) and args.max_message_mb > 0):
        raise ValueError(f"--max-message-mb must be a positive number of MiB, got {args.max_message_mb}")
    config = ServerConfig(host=args.host, port=args.port, token=token_option(args.token),
                          device=args.device, max_clients=args.max_clients, queue=args.queue,
                          idle_timeout=args.idle_timeout, meshes=args.meshes, processes=not args.threads,
                          limits=Limits(max_message_bytes=int(args.max_message_mb * 2**20)))
    totals = asyncio.run(serve_until_signal(config))
    print(f"photoreg serve: stopped after {totals['processed']} frames ({totals['dropped']} dropped, "
          f"{totals['errors']} errors)", flush=True)
    return 0

"""`photoreg serve` as a real background process on a free loopback port (README and Docker tests)."""
from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator

from websockets.exceptions import InvalidHandshake
from websockets.sync.client import connect


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def handshake(port: int, timeout: float = 2.0) -> bool:
    """True when a WebSocket handshake with 127.0.0.1:port completes."""
    try:
        with connect(f"ws://127.0.0.1:{port}", open_timeout=timeout):
            return True
    except (OSError, InvalidHandshake):
        return False


@contextlib.contextmanager
def serving(args: list[str], port: int, startup_s: float = 60.0) -> Iterator[subprocess.Popen]:
    """Run `photoreg serve ARGS` (ARGS must listen on `port`) until the block ends; fails if it never answers."""
    log = tempfile.TemporaryFile("w+")
    proc = subprocess.Popen([sys.executable, "-m", "photoreg", "serve", *args], stdout=log, stderr=subprocess.STDOUT,
                            text=True)
    try:
        deadline = time.monotonic() + startup_s
        while not handshake(port):
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                proc.wait()
                log.seek(0)
                raise RuntimeError(f"photoreg serve {' '.join(args)} did not answer on port {port}:\n{log.read()}")
            time.sleep(0.2)
        yield proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(timeout=30)
        log.close()

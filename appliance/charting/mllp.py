"""MLLP, HL7's minimal lower layer protocol: one message at a time over TCP, each in a start and end block.

A frame is ``0x0B``, the message (UTF-8, segments ended by carriage returns),
``0x1C 0x0D``. The receiver answers each frame with an ACK in a frame of its
own before the sender sends the next, which keeps the order.
"""

from __future__ import annotations

import socket

START = b"\x0b"
END = b"\x1c\x0d"
MAX_ANSWER_BYTES = 1 << 20
"""An answer longer than this is not an ACK: the connection is dropped rather than read on."""


def frame(message: str) -> bytes:
    """``message`` in MLLP's blocks.

    >>> frame("MSH|^~\\\\&\\r")
    b'\\x0bMSH|^~\\\\&\\r\\x1c\\r'
    """
    return START + message.encode("utf-8") + END


class MllpConnection:
    """A connection to an interface engine at ``host``:``port``; each call waits at most ``timeout_s``."""

    def __init__(self, host: str, port: int, timeout_s: float):
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        self._buffer = b""

    def exchange(self, message: str) -> str:
        """Send ``message`` and return the answer's text; OSError (``TimeoutError`` included) if none comes."""
        self.sock.sendall(frame(message))
        while True:
            end = self._buffer.find(END)
            if end >= 0:
                start = self._buffer.find(START)
                if start < 0 or start > end:
                    raise ConnectionError(f"an answer without MLLP's start block: {self._buffer[:40]!r}")
                answer, self._buffer = self._buffer[start + 1:end], self._buffer[end + len(END):]
                return answer.decode("utf-8", errors="replace")
            if len(self._buffer) > MAX_ANSWER_BYTES:
                raise ConnectionError(f"no MLLP end block in {len(self._buffer)} bytes")
            data = self.sock.recv(65536)
            if not data:
                raise ConnectionError("the interface engine closed the connection")
            self._buffer += data

    def close(self) -> None:
        self.sock.close()

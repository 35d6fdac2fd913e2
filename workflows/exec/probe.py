"""Is a Dask scheduler listening at an address? A check with a deadline, before connecting.

distributed's ``Client`` trusts what answers at the address: pointed at a web server (the
dashboard port, a proxy) it waits for ever, or reads an HTTP reply as a frame length and runs
out of memory. A Dask server speaks first: on every new TCP connection it sends its
handshake, an 8-byte frame length followed by that many bytes. :func:`check_scheduler` reads
exactly that, with a deadline, and refuses anything else in one line.
"""

import socket
import struct
import time
from urllib.parse import urlsplit

from pipeline.errors import ConfigError

MAX_HANDSHAKE = 1 << 16  # bytes; a handshake is a few hundred


def _fail(address: str, why: str) -> ConfigError:
    return ConfigError(f"cluster.address {address} is not a Dask scheduler: {why}; give the "
                       "address 'dask scheduler' prints (tcp://host:8786 by default, not the "
                       "dashboard's http port)")


def check_scheduler(address: str, timeout: float) -> None:
    """ConfigError unless ``address`` answers like a Dask server within ``timeout`` seconds.

    Only ``tcp://`` addresses (and ``host:port``) are checked; other protocols (tls, ucx,
    ...) are left to distributed.
    """
    text = address if "://" in address else f"tcp://{address}"
    parts = urlsplit(text)
    if parts.scheme in ("http", "https"):
        raise _fail(address, "it is a web address")
    if parts.scheme != "tcp":
        return
    try:
        host, port = parts.hostname, parts.port
    except ValueError:
        host, port = None, None
    if not host or port is None:
        raise ConfigError(f"cluster.address {address} is not host:port; give e.g. "
                          "tcp://scheduler-host:8786")
    deadline = time.monotonic() + timeout
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except OSError as err:
        reason = err.strerror or type(err).__name__
        raise ConfigError(f"cannot connect to the Dask scheduler at {address} "
                          f"(cluster.address) within {timeout:g} s: {reason}; start it with "
                          "'dask scheduler' or fix cluster.address") from None
    with sock:
        try:
            header = _receive(sock, 8, deadline)
            (length,) = struct.unpack("<Q", header)
            if not 0 < length <= MAX_HANDSHAKE:
                raise _fail(address, f"its first bytes ({header!r}) are not a Dask handshake")
            _receive(sock, length, deadline)
        except socket.timeout:
            raise _fail(address, f"it sent no Dask handshake within {timeout:g} s") from None
        except ConnectionError:
            raise _fail(address, "it closed the connection without a Dask handshake") from None
        except OSError as err:
            raise _fail(address, err.strerror or type(err).__name__) from None


def _receive(sock: socket.socket, n: int, deadline: float) -> bytes:
    data = bytearray()
    while len(data) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            raise socket.timeout()
        sock.settimeout(left)
        block = sock.recv(n - len(data))
        if not block:
            raise ConnectionError("closed")
        data += block
    return bytes(data)

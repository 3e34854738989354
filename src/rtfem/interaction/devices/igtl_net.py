"""rtfem's OpenIGTLink server: one thread with a selector over the listening socket and every
client, keeping serving whatever its peers do (the framing is :mod:`.igtl_wire`'s).

* several clients at once (at most ``max_clients``; one more is told so in the log and closed): an
  idle client holds nothing but its own socket;
* a deadline per message: a header and its body must arrive within ``message_timeout`` of the
  message's first byte, else that client is dropped with the reason (a drip of one byte a second
  holds nobody);
* bounded sizes: a body larger than its type's limit (:data:`.igtl_wire.BODY_LIMITS`) drops the
  client before anything is read; what waits to be sent keeps the newest message of each name (a
  slow reader gets fewer ``Organ`` frames, never an unbounded queue), and a client that reads
  nothing for ``send_timeout`` is dropped;
* a closed or reset socket is a disconnect: one line in the log (``rtfem.igtl``), no traceback,
  and never a loop on the dead socket (nor on a failing accept: it pauses a second);
* no signal handlers: the owner's :meth:`WireServer.close` stops it promptly from any thread.

Nothing a peer sends chooses where rtfem connects or writes: the server only listens where its
owner said, and passes each complete, framed message to its owner's handler.
"""

from __future__ import annotations

import errno
import ipaddress
import logging
import selectors
import socket
import threading
import time
from collections import OrderedDict
from typing import Callable

from ...errors import DeviceError
from .igtl_wire import HEADER_SIZE, FramingError, Header, crc64, parse_header

__all__ = ["WireServer", "Peer", "listen_socket"]

log = logging.getLogger("rtfem.igtl")

_CHUNK = 1 << 16
_STATUS_KEEP = 32  # Status messages waiting for one client, at most (the oldest go first)


def listen_socket(host: str, port: int) -> tuple[socket.socket, bool]:
    """A listening TCP socket on ``host``:``port`` and whether that address is a loopback one;
    DeviceError saying why not (an unknown address, one not of this machine, the port in use)."""
    if not isinstance(host, str) or not host.strip() or len(host) > 255 or not host.isprintable():
        raise DeviceError(f"OpenIGTLink: host={host!r} is not an address: give one of this machine, e.g. "
                          "127.0.0.1 (this machine only) or 0.0.0.0 (every interface)")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as exc:
        raise DeviceError(f"OpenIGTLink: cannot listen on {host!r}: unknown address "
                          f"({getattr(exc, 'strerror', None) or exc}); give an address of this machine, e.g. "
                          "127.0.0.1 (this machine only)") from None
    family, _, _, _, addr = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        sock.listen(16)
        sock.setblocking(False)
    except OSError as exc:
        sock.close()
        what = "choose another --port" if exc.errno == errno.EADDRINUSE else \
            "give an address of this machine, e.g. 127.0.0.1 (this machine only)"
        raise DeviceError(f"OpenIGTLink: cannot listen on {host}:{port} ({exc.strerror or exc}); {what}") from None
    try:
        loopback = ipaddress.ip_address(addr[0].split("%")[0]).is_loopback
    except ValueError:  # pragma: no cover - getaddrinfo gives numeric addresses
        loopback = False
    return sock, loopback


class Peer:
    """One client's connection: its address, what it sent of the message under way, and what waits
    to be sent to it."""

    def __init__(self, sock: socket.socket, address: str) -> None:
        self.sock, self.address = sock, address
        self.inbuf = bytearray()
        self.header: Header | None = None
        self.started: float | None = None  # when the first byte of the message under way came
        self.outbox: OrderedDict = OrderedDict()  # key -> bytes: the newest of each name
        self.current: memoryview | None = None   # the message being written
        self.blocked_since: float | None = None  # when a write last found the socket full
        self.closed = False
        self.writing = False  # registered for EVENT_WRITE
        self.received = 0
        self._seq = 0

    def __repr__(self) -> str:
        return f"client {self.address}"

    def queue(self, key: str | None, data: bytes) -> None:
        """Keep ``data`` to send: it replaces what waits under ``key`` (None: kept beside the others,
        at most a few dozen of those)."""
        if key is None:
            self._seq += 1
            key = ("#", self._seq)
            unique = [k for k in self.outbox if isinstance(k, tuple)]
            for k in unique[:max(0, len(unique) + 1 - _STATUS_KEEP)]:
                del self.outbox[k]
        else:
            self.outbox.pop(key, None)
        self.outbox[key] = data

    def pending(self) -> bool:
        return self.current is not None or bool(self.outbox)

    def state(self) -> str:
        """What it sent of the message under way, for a reason."""
        if self.header is None:
            return f"{len(self.inbuf)} of the {HEADER_SIZE} header bytes"
        h = self.header
        return f"{len(self.inbuf)} of the {h.body_size} body bytes of a {h.kind} {h.name!r}"


class WireServer:
    """An OpenIGTLink server on one thread (see the module's text).

    Parameters
    ----------
    host, port : where to listen.
    on_message : ``on_message(peer, header, body)``, called on the server's thread with each complete
        message (its body unchecked: :func:`.igtl_wire.content_of` checks it).
    on_close : ``on_close(peer, reason)``, called on the server's thread when a client goes.
    message_timeout : seconds from a message's first byte to its last.
    send_timeout : seconds a client may leave what is sent to it unread before it is dropped.
    max_clients : clients at once.

    Raises
    ------
    DeviceError
        The address or the port cannot be listened on.
    """

    def __init__(self, host: str, port: int, on_message: Callable, on_close: Callable | None = None, *,
                 message_timeout: float = 2.0, send_timeout: float = 10.0, max_clients: int = 16) -> None:
        crc64(b"")  # crcmod is there, or a DeviceError now
        self.host, self.port = host, port
        self.on_message, self.on_close = on_message, on_close
        self.message_timeout, self.send_timeout, self.max_clients = message_timeout, send_timeout, max_clients
        self._listen, self.loopback = listen_socket(host, port)
        self.port = self._listen.getsockname()[1]
        self._wake_r, self._wake_w = socket.socketpair()
        for s in (self._wake_r, self._wake_w):
            s.setblocking(False)
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._listen, selectors.EVENT_READ, "listen")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._peers: list[Peer] = []
        self._lock = threading.Lock()
        self._stopping = False
        self._closed = False
        self.error: str | None = None  # why the server's thread ended, if not by close()
        self.connections = 0
        self._accept_again: float | None = None  # when to listen again after a failed accept
        self._thread = threading.Thread(target=self._run, name="rtfem-igtl-wire", daemon=True)

    # ------------------------------------------------------------------ the owner's side (any thread)
    @property
    def clients(self) -> int:
        """The clients connected now."""
        return len(self._peers)

    def is_connected(self) -> bool:
        return bool(self._peers)

    def start(self) -> "WireServer":
        from ...threads import background

        if not self._thread.is_alive() and not self._closed:
            background(self._thread, self._request_stop)
            self._thread.start()
        return self

    def send(self, key: str | None, data: bytes, peer: Peer | None = None) -> None:
        """Send ``data`` (a packed message) to ``peer``, or to every client; under ``key`` the
        newest replaces an older one not yet begun (None: each is sent)."""
        with self._lock:
            for p in ([peer] if peer is not None else self._peers):
                if not p.closed:
                    p.queue(key, data)
        self._wake()

    def close(self, timeout: float = 2.0) -> None:
        """Stop serving: what waits to be sent gets a moment to go out, then every socket is closed.
        Idempotent, from any thread."""
        self._request_stop()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout)
        if not self._thread.is_alive() and not self._closed:
            self._teardown()

    def _request_stop(self) -> None:
        self._stopping = True
        self._wake()

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except OSError:  # full (a wake is pending already) or closed
            pass

    # ------------------------------------------------------------------ the server's thread
    def _run(self) -> None:
        try:
            while not self._stopping:
                events = self._sel.select(self._timeout(time.monotonic()))
                for key, mask in events:
                    if key.data == "listen":
                        self._accept()
                    elif key.data == "wake":
                        self._drain_wake()
                    else:
                        peer = key.data
                        if mask & selectors.EVENT_READ and not peer.closed:
                            self._read(peer)
                        if mask & selectors.EVENT_WRITE and not peer.closed:
                            self._write(peer)
                self._service(time.monotonic())
            self._flush(0.25)
        except BaseException as exc:  # noqa: BLE001 - the owner reads why, never a silent end
            self.error = f"{type(exc).__name__}: {exc}"
            log.error("the OpenIGTLink server stopped: %s", self.error)
        finally:
            self._teardown()

    def _timeout(self, now: float) -> float:
        t = 0.5 if self._accept_again is None else min(0.5, self._accept_again - now)
        for p in self._peers:
            if p.started is not None:
                t = min(t, p.started + self.message_timeout - now)
            if p.blocked_since is not None:
                t = min(t, p.blocked_since + self.send_timeout - now)
        return max(t, 0.001)

    def _drain_wake(self) -> None:
        try:
            while self._wake_r.recv(4096):
                pass
        except OSError:
            pass

    def _accept(self) -> None:
        while True:
            try:
                sock, addr = self._listen.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # e.g. out of file descriptors: tell, keep serving the others, retry soon
                log.warning("could not accept a client: %s; accepting again in 1 s", exc.strerror or exc)
                self._sel.unregister(self._listen)  # else the pending connection wakes the selector at once, again
                self._accept_again = time.monotonic() + 1.0
                return
            address = f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) else str(addr)
            if len(self._peers) >= self.max_clients:
                log.warning("refused client %s: %d clients are connected already (at most %d)", address,
                            len(self._peers), self.max_clients)
                sock.close()
                continue
            sock.setblocking(False)
            try:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError:  # pragma: no cover - not TCP
                pass
            peer = Peer(sock, address)
            with self._lock:
                self._peers.append(peer)
            self._sel.register(sock, selectors.EVENT_READ, peer)
            self.connections += 1
            log.info("client %s connected (%d connected)", address, len(self._peers))

    def _read(self, peer: Peer) -> None:
        try:
            data = peer.sock.recv(_CHUNK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._drop(peer, f"disconnected ({exc.strerror or exc})", warn=False)
            return
        if not data:
            how = "disconnected" if not peer.inbuf and peer.header is None else \
                f"disconnected in the middle of a message ({peer.state()})"
            self._drop(peer, how, warn=False)
            return
        if not peer.inbuf and peer.header is None:
            peer.started = time.monotonic()
        peer.inbuf += data
        self._parse(peer)

    def _parse(self, peer: Peer) -> None:
        buf, at = peer.inbuf, 0
        while not peer.closed:
            if peer.header is None:
                if len(buf) - at < HEADER_SIZE:
                    break
                try:
                    peer.header = parse_header(buf[at:at + HEADER_SIZE])
                except FramingError as exc:
                    self._drop(peer, str(exc))
                    return
                at += HEADER_SIZE
            size = peer.header.body_size
            if len(buf) - at < size:
                break
            header, body = peer.header, bytes(buf[at:at + size])
            at += size
            peer.header = None
            peer.received += 1
            try:
                self.on_message(peer, header, body)
            except Exception as exc:  # noqa: BLE001 - the owner's handler: tell, keep serving
                log.warning("a %s %r from %s was not handled: %s: %s", header.kind, header.name, peer.address,
                            type(exc).__name__, exc)
        del buf[:at]
        if peer.header is None and not buf:
            peer.started = None
        elif at:
            peer.started = time.monotonic()  # the next message began within this read

    def _write(self, peer: Peer) -> None:
        while True:
            if peer.current is None:
                with self._lock:
                    if not peer.outbox:
                        break
                    _, data = peer.outbox.popitem(last=False)
                peer.current = memoryview(data)
            try:
                n = peer.sock.send(peer.current)
            except (BlockingIOError, InterruptedError):
                if peer.blocked_since is None:
                    peer.blocked_since = time.monotonic()
                return
            except OSError as exc:
                self._drop(peer, f"disconnected ({exc.strerror or exc})", warn=False)
                return
            peer.blocked_since = None
            peer.current = peer.current[n:] if n < len(peer.current) else None

    def _service(self, now: float) -> None:
        """Deadlines, and the write interest of each client."""
        if self._accept_again is not None and now >= self._accept_again:
            self._accept_again = None
            self._sel.register(self._listen, selectors.EVENT_READ, "listen")
        for peer in list(self._peers):
            if peer.started is not None and now - peer.started > self.message_timeout:
                self._drop(peer, f"sent {peer.state()} in {now - peer.started:.1f} s: a message must arrive within "
                                 f"{self.message_timeout:g} s of its first byte")
            elif peer.blocked_since is not None and now - peer.blocked_since > self.send_timeout:
                self._drop(peer, f"read nothing sent to it for {self.send_timeout:g} s")
            if peer.closed:
                continue
            if peer.pending() and not peer.writing:
                self._write(peer)  # most writes go at once; a full socket waits for the selector
            want = peer.pending() and not peer.closed
            if want != peer.writing and not peer.closed:
                self._sel.modify(peer.sock, selectors.EVENT_READ | (selectors.EVENT_WRITE if want else 0), peer)
                peer.writing = want

    def _drop(self, peer: Peer, reason: str, warn: bool = True) -> None:
        if peer.closed:
            return
        peer.closed = True
        (log.warning if warn else log.info)("client %s %s%s", peer.address, "dropped: " if warn else "", reason)
        with self._lock:
            if peer in self._peers:
                self._peers.remove(peer)
            peer.outbox.clear()
        try:
            self._sel.unregister(peer.sock)
        except (KeyError, ValueError):
            pass
        peer.sock.close()
        if self.on_close is not None:
            try:
                self.on_close(peer, reason)
            except Exception as exc:  # noqa: BLE001 - the owner's handler: tell, keep serving
                log.warning("the end of %s was not handled: %s: %s", peer.address, type(exc).__name__, exc)

    def _flush(self, seconds: float) -> None:
        """What waits to be sent (a last zero force) gets ``seconds`` to go out."""
        end = time.monotonic() + seconds
        for peer in list(self._peers):
            while peer.pending() and not peer.closed and time.monotonic() < end:
                self._write(peer)
                if peer.pending() and not peer.closed:
                    time.sleep(0.005)

    def _teardown(self) -> None:
        if self._closed:
            return
        self._closed = True
        # the listening socket first: a client that reads its end of the link finds the port free already
        for s in (self._listen, self._wake_r, self._wake_w):
            try:
                s.close()
            except OSError:  # pragma: no cover
                pass
        for peer in list(self._peers):
            peer.closed = True
            try:
                peer.sock.close()
            except OSError:  # pragma: no cover
                pass
        with self._lock:
            self._peers.clear()
        try:
            self._sel.close()
        except Exception:  # noqa: BLE001 - closing anyway
            pass

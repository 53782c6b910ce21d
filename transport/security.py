"""CurveZMQ helpers: authenticated, encrypted ZeroMQ links (RFC 26 CurveZMQ, ZAP RFC 27).

Keys are ZeroMQ certificate files as written by ``zmq.auth.create_certificates``:
``<name>.key`` (public) and ``<name>.key_secret`` (public + secret). The side that binds is
the CURVE server; it holds its secret certificate and a folder of allowed client public
certificates, and a ZAP authenticator thread rejects every other client. A client holds its
own secret certificate and the server's public one.

``python -m transport.security keygen DIR NAME`` writes a key pair.
"""

from __future__ import annotations

import ipaddress
import sys
from dataclasses import dataclass
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

_authenticators: dict[int, ThreadAuthenticator] = {}


class KeyError_(ValueError):
    """A key file that cannot be used; the message names the file."""


def keygen(directory: str | Path, name: str) -> tuple[Path, Path]:
    """Write ``name.key`` and ``name.key_secret`` in ``directory``; returns (public, secret)."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    pub, sec = zmq.auth.create_certificates(str(d), name)
    return Path(pub), Path(sec)


def _load(path: str | Path, secret: bool) -> tuple[bytes, bytes | None]:
    p = Path(path)
    try:
        pub, sec = zmq.auth.load_certificate(str(p))
    except (OSError, ValueError) as exc:
        raise KeyError_(f"{p}: not a ZeroMQ certificate ({exc})") from None
    if secret and sec is None:
        raise KeyError_(f"{p}: holds no secret key (give the .key_secret file)")
    return pub, sec


def make_server(sock: zmq.Socket, secret_file: str | Path, allowed_dir: str | Path) -> None:
    """Make ``sock`` a CURVE server accepting only clients whose public keys are in ``allowed_dir``.

    Call before bind. Starts (once per context) a ZAP authenticator thread.
    """
    allowed = Path(allowed_dir)
    if not allowed.is_dir():
        raise KeyError_(f"{allowed}: no such folder of allowed client keys")
    pub, sec = _load(secret_file, secret=True)
    ctx = sock.context
    auth = _authenticators.get(id(ctx))
    if auth is None:
        auth = ThreadAuthenticator(ctx)
        auth.start()
        _authenticators[id(ctx)] = auth
    auth.configure_curve(domain="*", location=str(allowed))
    sock.curve_secretkey = sec
    sock.curve_publickey = pub
    sock.curve_server = True


def make_client(sock: zmq.Socket, secret_file: str | Path, server_public_file: str | Path) -> None:
    """Make ``sock`` a CURVE client of the server whose public certificate is given. Call before connect."""
    pub, sec = _load(secret_file, secret=True)
    server_pub, _ = _load(server_public_file, secret=False)
    sock.curve_secretkey = sec
    sock.curve_publickey = pub
    sock.curve_serverkey = server_pub


@dataclass
class Curve:
    """CURVE settings for one socket: our secret certificate, plus the allowed client keys
    (when we are the server, i.e. we bind) or the server's public certificate (when we connect)."""

    secret: str | Path
    allowed: str | Path | None = None
    server_public: str | Path | None = None

    def apply(self, sock: zmq.Socket, server: bool) -> None:
        if server:
            if self.allowed is None:
                raise KeyError_("a CURVE server needs a folder of allowed client keys")
            make_server(sock, self.secret, self.allowed)
        else:
            if self.server_public is None:
                raise KeyError_("a CURVE client needs the server's public key")
            make_client(sock, self.secret, self.server_public)


def curve_from_flags(secret: str | None, clients: str | None, server: str | None) -> Curve | None:
    """The Curve settings from the command-line flags, or None when none is given. Client or
    server keys without our secret certificate are an error: never plaintext by surprise."""
    if not secret:
        given = [f for f, v in (("--curve-clients", clients), ("--curve-server", server)) if v]
        if given:
            raise ValueError(f"{' and '.join(given)} given without --curve-secret: CurveZMQ needs our secret "
                             "certificate (refusing to run in plaintext)")
        return None
    return Curve(secret, clients, server)


LOOPBACK = "127.0.0.1"


def zmq_address(addr: str, interface: str | None = None) -> str:
    """A full ZeroMQ endpoint from ``PORT``, ``HOST:PORT`` or ``tcp://HOST:PORT``.

    A bare port goes to ``interface`` (default 127.0.0.1); port 0 or ``*`` is any free port. A
    host that is not loopback is refused unless ``interface`` names it: nothing is exposed
    beyond this machine by accident.
    """
    addr = str(addr).strip()
    if addr.isdigit() or addr == "*":
        return f"tcp://{interface or LOOPBACK}:{'*' if addr in ('0', '*') else addr}"
    if addr.endswith(":0"):
        addr = addr[:-2] + ":*"  # ZeroMQ spells "any free port" as *
    if "://" not in addr:
        addr = "tcp://" + addr
    scheme, rest = addr.split("://", 1)
    if scheme in ("ipc", "inproc"):
        return addr  # stays on this machine
    if scheme in ("pgm", "epgm", "norm"):
        if not interface:
            raise ValueError(f"{addr!r}: {scheme}:// is multicast and leaves this machine; pass --interface to use it")
        return addr
    if scheme not in ("tcp", "ws", "wss"):
        raise ValueError(f"{addr!r}: ZeroMQ endpoints here are tcp://HOST:PORT or ipc://PATH (not {scheme}://)")
    if scheme != "tcp" and not zmq.has(scheme):
        raise ValueError(f"{addr!r}: this libzmq build has no {scheme}:// transport")
    hostport = rest.split("/", 1)[0]
    if ":" not in hostport:
        raise ValueError(f"{addr!r}: no port (give HOST:PORT, port 0 or * for any free port)")
    host, port = hostport.rsplit(":", 1)
    if port != "*" and not (port.isdigit() and 0 < int(port) < 65536):
        raise ValueError(f"{addr!r}: port {port!r} is not a number from 1 to 65535 (or 0/* for any)")
    check_host(host, interface)
    return addr


def udp_address(addr: str, default_port: int, interface: str | None = None) -> tuple[str, int]:
    """``(host, port)`` from ``PORT``, ``HOST`` or ``HOST:PORT`` with the same loopback rule."""
    addr = str(addr).strip()
    if addr.isdigit():
        host, port = interface or LOOPBACK, int(addr)
    elif ":" in addr:
        host, p = addr.rsplit(":", 1)
        try:
            port = int(p)
        except ValueError:
            raise ValueError(f"{addr!r}: port {p!r} is not a number") from None
        if not 0 <= port < 65536:
            raise ValueError(f"{addr!r}: port {port} is not in 0..65535")
    else:
        host, port = addr, default_port
    check_host(host, interface)
    return host, port


def check_host(host: str, interface: str | None) -> None:
    host = host.strip("[]")
    if host in ("localhost", LOOPBACK, "::1") or host == interface:
        return
    try:
        if ipaddress.ip_address(host).is_loopback:
            return
    except ValueError:
        pass
    raise ValueError(f"{host} is not this machine's loopback interface; pass --interface {host} to use it")


def stop_authenticators() -> None:
    for auth in _authenticators.values():
        auth.stop()
    _authenticators.clear()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 3 or argv[0] != "keygen":
        print("usage: python -m transport.security keygen DIR NAME", file=sys.stderr)
        return 2
    for p in keygen(argv[1], argv[2]):
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())

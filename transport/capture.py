"""``livecap run --qtm-in`` / ``--natnet-in``: the capture-system source for HOST[:PORT].

This module only chooses and builds; the sources import what they share from
``transport.capture_queue``, never this module, so the arrows run one way.
"""

from __future__ import annotations

from transport.capture_queue import endpoint
from transport.security import check_host


def host_port(text: str, default: int) -> tuple[str, int]:
    """``(host, port)`` from ``HOST``, ``HOST:PORT``, an IPv6 address (``::1``) or ``[IPv6]:PORT``."""
    text = text.strip()
    host, port = text, ""
    if text.startswith("["):
        host, sep, rest = text[1:].partition("]")
        if not sep or (rest and not rest.startswith(":")):
            raise ValueError(f"{text!r}: expected [IPv6]:PORT")
        port = rest[1:]
    elif text.count(":") == 1:
        host, port = text.split(":")
    try:
        value = int(port) if port else default
    except ValueError:
        raise ValueError(f"{text!r}: expected HOST[:PORT] (port {port!r} is not a number)") from None
    if not 0 < value < 65536:
        raise ValueError(f"{text!r}: port {value} is not in 1..65535")
    return host or "127.0.0.1", value


def capture_source(qtm: str | None, natnet: str | None, labels: list[str], unlabelled: bool,
                   idle_timeout: float | None, interface: str | None = None):
    """The QTM RT or NatNet source and its description for the ``ready`` line. A server that is
    not on this machine's loopback must be named by ``interface`` (transport/security.py's rule)."""
    if qtm:
        from transport.qtm import DEFAULT_PORT, QtmSource

        host, port = host_port(qtm, DEFAULT_PORT)
        check_host(host, interface)
        return (QtmSource(host, port, labels, unlabelled=unlabelled, idle_timeout=idle_timeout),
                f"qtm-in {endpoint(host, port)}")
    from transport.natnet import DEFAULT_PORT, NatNetSource

    host, port = host_port(natnet, DEFAULT_PORT)
    check_host(host, interface)
    return (NatNetSource(host, port, labels, unlabelled=unlabelled, idle_timeout=idle_timeout),
            f"natnet-in {endpoint(host, port)}")

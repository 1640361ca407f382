"""bound_address: the one place every network simulator (E71 TCP/UDP, the fixed-buffer
simulator, S5-LAN, FETCH/WRITE, ...) turns its bound socket address into host, port and URL."""

from __future__ import annotations

from plcstack.sim.base import bound_address
from plcstack.url import parse_url


def test_an_ipv4_address_without_options() -> None:
    assert bound_address(("127.0.0.1", 40001), "e71+tcp") == (
        "127.0.0.1",
        40001,
        "e71+tcp://127.0.0.1:40001",
    )


def test_an_address_with_options() -> None:
    assert bound_address(("127.0.0.1", 5002), "e71+udp", "code=ascii&procedure=0") == (
        "127.0.0.1",
        5002,
        "e71+udp://127.0.0.1:5002?code=ascii&procedure=0",
    )


def test_an_ipv6_host_is_bracketed_so_the_url_parses_back() -> None:
    host, port, url = bound_address(("::1", 5003, 0, 0), "s5lan")
    assert (host, port, url) == ("::1", 5003, "s5lan://[::1]:5003")
    parsed = parse_url(url)
    assert (parsed.host, parsed.port) == ("::1", 5003)

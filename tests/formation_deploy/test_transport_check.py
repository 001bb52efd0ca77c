"""Secure mode fails closed: a process with a UDP socket refuses to run when FORMATION_SECURE=1."""

from __future__ import annotations

import socket

import pytest

from formation_deploy.transport_check import InsecureTransportError, check_secure_transport, udp_sockets


def test_udp_socket_of_this_process_is_found_and_refused_in_secure_mode() -> None:
    """A bound UDP socket shows in udp_sockets(); secure mode then raises, naming the profile."""
    before = udp_sockets()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        assert any(addr.endswith(f":{port:04X}") for addr in udp_sockets())
        with pytest.raises(InsecureTransportError, match=r"/p/agent_1\.xml did not apply"):
            check_secure_transport({"FORMATION_SECURE": "1", "FASTRTPS_DEFAULT_PROFILES_FILE": "/p/agent_1.xml"})
        check_secure_transport({})  # not in secure mode: no check
    assert udp_sockets() == before

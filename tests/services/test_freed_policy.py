"""Where FreeD packets may go (`FreeDPolicy`), address by address, and what the host of a
stored receiver may be."""

from __future__ import annotations

import asyncio
from ipaddress import ip_address, ip_network
from pathlib import Path

import pytest

from app.services.freed import FreeDDestination, FreeDPolicy, FreeDSenders, FreeDUnusable, _stored_host_refusal
from app.settings import Settings

SPECIAL = {
    "127.0.0.1": "loopback", "127.255.0.9": "loopback", "::1": "loopback", "::ffff:127.0.0.1": "loopback",
    "169.254.169.254": "link-local", "fe80::1": "link-local", "::ffff:169.254.169.254": "link-local",
    "224.0.0.1": "multicast", "239.255.255.250": "multicast", "ff02::1": "multicast",
    "255.255.255.255": "broadcast", "0.0.0.0": "unspecified", "0.1.2.3": "unspecified", "::": "unspecified",
    "240.0.0.1": "reserved", "fec0::1": "site-local",
}
ORDINARY = ["192.168.1.40", "10.0.0.7", "172.16.3.4", "100.64.0.1", "8.8.8.8", "2001:db8::1", "fd00::5"]


@pytest.mark.parametrize(("address", "kind"), SPECIAL.items())
def test_special_addresses_are_refused_unless_listed(address: str, kind: str) -> None:
    why = FreeDPolicy().refusal(ip_address(address), own=False)
    assert why is not None and kind in why and "freed_allowed_networks" in why
    listed = FreeDPolicy(allowed_networks=(ip_network(address),))
    assert listed.refusal(ip_address(address), own=False) is None
    assert listed.refusal(ip_address(address), own=True) is None


@pytest.mark.parametrize("address", ORDINARY)
def test_an_environments_receiver_may_be_anywhere_ordinary_a_connections_only_where_listed(address: str) -> None:
    policy = FreeDPolicy(connection_receivers=True, allowed_networks=(ip_network("192.168.1.0/24"),))
    assert policy.refusal(ip_address(address), own=False) is None
    own = policy.refusal(ip_address(address), own=True)
    assert (own is None) == (address == "192.168.1.40")


def test_a_stored_host_is_checked_as_far_as_known_without_a_lookup() -> None:
    policy = FreeDPolicy(allowed_networks=(ip_network("127.0.0.1/32"),))
    assert _stored_host_refusal("127.0.0.1", policy) is None
    assert "link-local" in (_stored_host_refusal("169.254.169.254", policy) or "")
    # localhost means ::1 as well, which the list does not hold.
    assert "::1 is a loopback" in (_stored_host_refusal("localhost", policy) or "")
    assert "loopback" in (_stored_host_refusal("db.localhost", FreeDPolicy()) or "")
    assert _stored_host_refusal("unreal.studio.example", FreeDPolicy()) is None  # checked when a connection uses it


def test_a_connections_own_receiver_needs_a_listed_network(tmp_path: Path) -> None:
    senders = FreeDSenders(Settings(data_dir=tmp_path, freed_connection_receivers=True))

    async def check() -> None:
        with pytest.raises(FreeDUnusable, match="lists no network"):
            await senders.open(FreeDDestination("192.168.1.40", 40000, 1, own=True))
        with pytest.raises(FreeDUnusable, match="224.0.0.1 is a multicast"):
            await senders.open(FreeDDestination("224.0.0.1", 40000, 1))
        sender = await senders.open(FreeDDestination("192.168.1.40", 40000, 1))  # a socket; nothing is sent
        assert sender.address == ("192.168.1.40", 40000)
        sender.close()

    try:
        asyncio.run(check())
    finally:
        senders.close()

"""Ports for the servers roadgrip starts: outside the kernel's ephemeral range, free, distinct."""

import socket

from roadgrip.cloud.localhost import HOST, ephemeral_range, free_ports, pick_pool


def test_ports_are_free_distinct_and_outside_the_ephemeral_range():
    low, high = ephemeral_range()
    ports = free_ports(20)
    assert len(set(ports)) == 20
    assert all(not low <= p <= high for p in ports)
    for p in ports:
        with socket.socket() as s:
            s.bind((HOST, p))


def test_a_port_in_use_is_never_picked():
    held = []
    try:
        for p in free_ports(50):
            s = socket.socket()
            s.bind((HOST, p))
            s.listen()
            held.append(s)
        taken = {s.getsockname()[1] for s in held}
        assert not taken & set(free_ports(50))
    finally:
        for s in held:
            s.close()


def test_the_pool_is_the_larger_side_of_the_ephemeral_range():
    assert pick_pool((32768, 60999)) == range(10000, 32768)
    assert pick_pool((10500, 40000)) == range(40001, 65536)
    assert pick_pool((1024, 65535)) == range(1024, 65536)  # no room outside: the range itself


def test_an_unreadable_range_file_falls_back_to_the_kernel_default(tmp_path):
    assert ephemeral_range(tmp_path / "missing") == (32768, 60999)
    (tmp_path / "range").write_text("20000\t30000\n")
    assert ephemeral_range(tmp_path / "range") == (20000, 30000)

"""The supervisor's orders pipe to a worker (``msctl restart --only``), read as the worker does."""

from __future__ import annotations

import os

import pytest
from conftest import wait_until

from components.executor.orders import MAX_LINE, REBUILD, Orders, encode


def test_orders_are_read_line_by_line_and_only_known_ones_handed_on() -> None:
    reader, writer = os.pipe()
    got: list[tuple[str, str]] = []
    orders = Orders(reader, lambda order, argument: got.append((order, argument))).start()
    os.write(writer, encode(REBUILD, "limb1/joint_manager"))
    os.write(writer, b"explode now\n" + b"x" * (MAX_LINE + 10))  # unknown, then overlong
    os.write(writer, b"\n" + encode(REBUILD, "limb1/health")[:7])  # half a line...
    os.write(writer, encode(REBUILD, "limb1/health")[7:])  # ...completed later
    wait_until(lambda: len(got) == 2, 10.0)
    assert got == [(REBUILD, "limb1/joint_manager"), (REBUILD, "limb1/health")]
    os.close(writer)  # the supervisor is gone: the reader ends
    orders._thread.join(timeout=10.0)
    assert not orders._thread.is_alive()
    os.close(reader)


def test_an_order_argument_is_one_line() -> None:
    with pytest.raises(ValueError, match="one line"):
        encode(REBUILD, "limb1/joint_manager\nrebuild sim/simulator")

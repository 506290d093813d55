"""Close paths: what a component's close goes on past is logged, never lost."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import pytest
from conftest import resolved_assembly

from components.build import build_component


class _Port:
    """A resource that closes cleanly and counts it (the motor bus beside the broken one)."""

    def __init__(self) -> None:
        self.closed = 0

    def close(self) -> None:
        self.closed += 1


def test_a_resource_that_fails_to_close_is_logged_and_the_others_still_close(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A device file whose descriptor went away under it (a USB adapter pulled) fails to
    close with EBADF: ``BuiltComponent.close`` says so at WARNING, naming the resource and
    the error, and still closes the resources listed before it."""
    assembly = resolved_assembly(tmp_path, "dragon")
    built = build_component(assembly.component("limb1/location_tip"), assembly)
    earlier = _Port()
    device = (tmp_path / "ttyUSB0").open("wb", buffering=0)
    os.close(device.fileno())  # the descriptor is gone; the file object does not know yet
    built.resources += [earlier, device]

    with caplog.at_level(logging.WARNING, logger="components.build"):
        built.close()

    (record,) = [r for r in caplog.records if r.name == "components.build"]
    assert record.levelno == logging.WARNING
    message = record.getMessage()
    assert message.startswith("/limb1/location_tip: closing ")
    assert "ttyUSB0" in message and "Bad file descriptor" in message
    assert record.exc_info is not None and isinstance(record.exc_info[1], OSError)
    assert earlier.closed == 1
    assert device.closed

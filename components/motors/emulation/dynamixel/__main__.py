"""``python -m components.motors.emulation.dynamixel --ids 1,2,3``: serve a chain for a demo."""

from __future__ import annotations

import argparse
import contextlib
import time

from components.motors.emulation.dynamixel.chain import EmulatedDynamixelChain
from components.motors.emulation.dynamixel.datasheet import MODELS


def main(argv: list[str] | None = None) -> None:
    """Serve an emulated chain until interrupted, printing the device path to use."""
    parser = argparse.ArgumentParser(
        description="Serve an emulated Dynamixel chain on a pseudo-terminal."
    )
    parser.add_argument("--ids", default="1,2,3", help="comma-separated servo ids")
    parser.add_argument("--model", default="XM430-W350", choices=sorted(MODELS))
    args = parser.parse_args(argv)
    ids = [int(part) for part in args.ids.split(",") if part.strip()]
    with EmulatedDynamixelChain(ids=ids, model=args.model) as chain:
        print(chain.port, flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            while True:
                time.sleep(1.0)


if __name__ == "__main__":
    main()

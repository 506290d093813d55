"""The awaitable a motion returns, shared by the joint and IK syncers."""

from __future__ import annotations

import asyncio
from collections.abc import Generator
from typing import Any


class Motion:
    """One motion in progress. ``await motion`` gives True when it arrived, False when a newer
    motion (or a stop) cancelled it first.

    A cancelled motion resolves to False rather than raising, so a script that starts a
    motion and then changes its mind is not interrupted by its own first request.

    Args:
        description: What it does, for messages (``lerp limb1 (7 joints)``).
    """

    def __init__(self, description: str) -> None:
        self.description = description
        self._future: asyncio.Future[bool] = asyncio.get_running_loop().create_future()

    def __await__(self) -> Generator[Any, None, bool]:
        return self._future.__await__()

    def __repr__(self) -> str:
        if not self._future.done():
            state = "running"
        elif self._future.exception() is not None:
            state = "failed"
        else:
            state = "arrived" if self._future.result() else "cancelled"
        return f"<Motion {self.description}: {state}>"

    async def wait(self, timeout: float | None = None) -> bool:
        """Wait for the end; True when arrived.

        Raises:
            TimeoutError: If ``timeout`` seconds pass first (the motion goes on).
        """
        try:
            return await asyncio.wait_for(asyncio.shield(self._future), timeout)
        except TimeoutError:
            raise TimeoutError(f"{self.description} did not arrive within {timeout:g} s") from None

    def done(self) -> bool:
        """Whether it ended (arrived, cancelled or failed)."""
        return self._future.done()

    @property
    def arrived(self) -> bool:
        """Whether it ended by arriving."""
        f = self._future
        return f.done() and f.exception() is None and f.result()

    def finish(self, arrived: bool) -> None:
        """End it (used by the syncers); later calls are ignored."""
        if not self._future.done():
            self._future.set_result(arrived)

    def fail(self, error: BaseException) -> None:
        """End it with an error (used by the syncers)."""
        if not self._future.done():
            self._future.set_exception(error)

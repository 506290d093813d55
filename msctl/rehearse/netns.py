"""Network namespaces and TUN devices: entering a computer's namespace, making its radio.

:func:`run_in_netns` runs a function inside a named network namespace (on a thread of its
own, so the caller's namespace never changes); :func:`open_tun` makes a computer's TUN
device there; :func:`ip_in` runs ``ip`` against a namespace.
"""

from __future__ import annotations

import ctypes
import fcntl
import os
import struct
import subprocess
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from msctl.errors import MsctlError, NotFoundError

T = TypeVar("T")

_CLONE_NEWNET = 0x40000000
_TUNSETIFF = 0x400454CA
_IFF_TUN = 0x0001
_IFF_NO_PI = 0x1000


def netns_path(netns: str) -> Path:
    """The file of a named network namespace (as ``ip netns add`` makes it)."""
    return Path("/run/netns") / netns


def run_in_netns(netns: str, function: Callable[[], T]) -> T:
    """Call ``function`` inside network namespace ``netns`` and return what it returns.

    It runs on a new thread that enters the namespace (setns only moves the calling thread)
    and then ends, so the caller's namespace never changes. Sockets and devices made there
    stay in that namespace after it returns: a socket opened this way talks from that
    computer. Needs CAP_SYS_ADMIN over it: root, or the user namespace that owns it.

    Raises:
        NotFoundError: No such namespace.
        OSError: The namespace could not be entered; or what ``function`` raised.
    """
    outcome: dict[str, Any] = {}

    def inside() -> None:
        try:
            try:
                fd = os.open(netns_path(netns), os.O_RDONLY | os.O_CLOEXEC)
            except FileNotFoundError:
                raise NotFoundError(
                    f"no network namespace {netns!r} (no {netns_path(netns)})",
                    hint="`ip netns list` shows the ones there are",
                ) from None
            try:
                libc = ctypes.CDLL(None, use_errno=True)
                if libc.setns(fd, _CLONE_NEWNET) != 0:
                    code = ctypes.get_errno()
                    raise OSError(
                        code,
                        f"cannot enter network namespace {netns!r}: {os.strerror(code)}",
                    )
            finally:
                os.close(fd)
            outcome["value"] = function()
        except BaseException as error:
            outcome["error"] = error

    thread = threading.Thread(target=inside, name=f"netns-{netns}", daemon=True)
    thread.start()
    thread.join()
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]


def open_tun(netns: str, device: str) -> int:
    """Create TUN device ``device`` in namespace ``netns`` (no packet info, non-blocking).

    It is not persistent: it goes away when the returned descriptor is closed. IPv6 is
    turned off on it, so the kernel sends no router solicitations or MLD reports through
    the radio.

    Returns:
        The device's descriptor.
    """

    def create() -> int:
        fd = os.open("/dev/net/tun", os.O_RDWR | os.O_CLOEXEC | os.O_NONBLOCK)
        try:
            request = struct.pack("16sH22x", device.encode(), _IFF_TUN | _IFF_NO_PI)
            fcntl.ioctl(fd, _TUNSETIFF, request)
        except OSError as error:
            os.close(fd)
            raise OSError(
                error.errno,
                f"cannot create TUN device {device!r} in {netns!r}: {error.strerror}",
            ) from error
        # /proc/sys/net shows the namespace of the thread that opens it: this one.
        ipv6 = Path(f"/proc/sys/net/ipv6/conf/{device}/disable_ipv6")
        if ipv6.exists():
            ipv6.write_text("1")
        return fd

    return run_in_netns(netns, create)


def ip_in(netns: str, *args: str) -> None:
    """Run ``ip -n NETNS ARGS``.

    Raises:
        MsctlError: If it fails (its message is ``ip``'s).
    """
    command = ["ip", "-n", netns, *args]
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        raise MsctlError(
            f"`{' '.join(command)}` failed: {result.stderr.strip() or result.returncode}",
            exit_code=3,
        )

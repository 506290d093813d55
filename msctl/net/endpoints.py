"""Zenoh endpoints as this computer's routers use them: where a router may listen, whether a
link leaves the computer, and who holds a port a router cannot bind.

A router that cannot listen fails the same way on every restart: the port is another
program's, or the address is not this computer's. :func:`check_listen` finds that out before
the router starts (a test bind, the way Zenoh binds), so the error comes at once, in one line
naming the endpoint, who holds it when this computer can tell, and what to do, rather than
after a supervisor has restarted the router five times.
"""

from __future__ import annotations

import contextlib
import errno
import ipaddress
import os
import socket
from dataclasses import dataclass
from pathlib import Path

#: Link protocols whose traffic is encrypted and authenticated (mutual TLS in msctl's fleet).
ENCRYPTED = frozenset({"tls", "quic"})
#: Link protocols that listen on a TCP port (a bind check applies to them).
TCP_BASED = frozenset({"tcp", "tls", "ws"})
#: Link protocols that never leave the computer, whatever their address.
LOCAL_ONLY = frozenset({"unixsock-stream", "unixpipe", "vsock", "shm"})
#: Addresses that listen on every interface.
WILDCARDS = frozenset({"", "0.0.0.0", "::"})


class EndpointError(ValueError):
    """An endpoint a router cannot use; the message names it and says what to do."""


@dataclass(frozen=True)
class Endpoint:
    """A parsed Zenoh endpoint (``tcp/127.0.0.1:7447``).

    Attributes:
        text: The endpoint as written.
        protocol: ``tcp``, ``tls``, ``udp`` ...
        host: The address or name, IPv6 brackets removed (``""`` when none).
        port: The port, or ``None`` when there is none (a unix socket's path).
    """

    text: str
    protocol: str
    host: str
    port: int | None

    @property
    def loopback(self) -> bool:
        """Whether the address is this computer's loopback (``localhost``, 127/8, ::1)."""
        return is_loopback(self.host)

    @property
    def wildcard(self) -> bool:
        """Whether it listens on every interface (``0.0.0.0``, ``[::]``)."""
        return self.host in WILDCARDS

    @property
    def encrypted(self) -> bool:
        """Whether its links are encrypted (TLS, QUIC)."""
        return self.protocol in ENCRYPTED

    @property
    def leaves_computer(self) -> bool:
        """Whether links on it can come from, or go to, another computer."""
        return self.protocol not in LOCAL_ONLY and not self.loopback


def parse(text: str) -> Endpoint:
    """Read an endpoint; Zenoh's ``?metadata`` and ``#config`` suffixes are ignored.

    Raises:
        EndpointError: If it has no protocol (``tcp/``, ``tls/`` ...).
    """
    protocol, slash, address = text.strip().partition("/")
    if not slash or not protocol:
        raise EndpointError(f"endpoint {text!r} lacks a protocol; write it like tcp/127.0.0.1:7447")
    address = address.split("#", 1)[0].split("?", 1)[0]
    host, colon, port = address.rpartition(":")
    if not colon or not port.isdigit():
        return Endpoint(text, protocol, address.strip("[]"), None)
    return Endpoint(text, protocol, host.strip("[]"), int(port))


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or ``localhost``) is this computer's loopback."""
    if host.lower() in ("localhost", "localhost.localdomain", "ip6-localhost"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def covers(wide: str, narrow: str) -> bool:
    """Whether listening on ``wide`` also listens where ``narrow`` would: the same protocol
    and port on a wildcard address (``tcp/0.0.0.0:7447`` covers ``tcp/127.0.0.1:7447``).

    Two such endpoints cannot both be listened on by one router: the second bind fails with
    "address in use" inside the same process.
    """
    a, b = parse(wide), parse(narrow)
    return (
        a.protocol == b.protocol
        and a.port is not None
        and a.port == b.port
        and a.wildcard
        and (b.loopback or b.wildcard)
    )


# --------------------------------------------------------------------------- listening
def check_listen(text: str, setting: str = "MSCTL_ROUTER_LISTEN") -> None:
    """Whether a router of this computer can listen on ``text``, by binding it a moment.

    Only TCP-based endpoints with a fixed port are checked (``:0`` always binds). The socket
    is bound with ``SO_REUSEADDR``, as Zenoh's listeners are, so a port left in TIME_WAIT by
    a router that just stopped is not mistaken for a taken one.

    Args:
        text: The endpoint.
        setting: Where it came from, named in the fix (``MSCTL_ROUTER_LISTEN``).

    Raises:
        EndpointError: The port is taken (by whom, when this computer can tell), the address
            is not this computer's, or its name does not resolve.
    """
    endpoint = parse(text)
    if endpoint.protocol not in TCP_BASED or not endpoint.port:
        return
    try:
        infos = socket.getaddrinfo(
            endpoint.host or None,
            endpoint.port,
            type=socket.SOCK_STREAM,
            flags=socket.AI_PASSIVE,
        )
    except socket.gaierror as exc:
        raise EndpointError(
            f"cannot listen on {text}: {endpoint.host!r} does not resolve ({exc.strerror}); "
            f"use one of this computer's addresses (or 0.0.0.0) in {setting}"
        ) from None
    family, kind, proto, _, address = infos[0]  # the one a listener binds first
    try:
        sock = socket.socket(family, kind, proto)
    except OSError:
        return  # no such family here (IPv6 off): Zenoh says what it makes of it
    with sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if family == socket.AF_INET6 and endpoint.wildcard:
            # [::] takes IPv4 too on Linux (dual stack), as Zenoh's listener does.
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 0)
        try:
            sock.bind(address)
        except OSError as exc:
            raise EndpointError(_bind_failure(endpoint, exc, setting)) from None


def _bind_failure(endpoint: Endpoint, exc: OSError, setting: str) -> str:
    if exc.errno == errno.EADDRINUSE:
        who, fix = holder(endpoint.port or 0)
        if fix.endswith("another port"):
            fix += f" in {setting}"
        return f"cannot listen on {endpoint.text}: port {endpoint.port} is taken by {who}; {fix}"
    if exc.errno == errno.EADDRNOTAVAIL:
        return (
            f"cannot listen on {endpoint.text}: {endpoint.host} is not an address of this "
            f"computer; use one of its own (`ip -brief address`) or 0.0.0.0 in {setting}"
        )
    if exc.errno == errno.EACCES:
        return (
            f"cannot listen on {endpoint.text}: port {endpoint.port} needs root (below 1024); "
            f"use a port above 1023 in {setting}"
        )
    return f"cannot listen on {endpoint.text}: {exc.strerror or exc}; change {setting}"


# --------------------------------------------------------------------------- who holds a port
def holder(port: int) -> tuple[str, str]:
    """Who listens on TCP ``port`` of this computer, and what to do about it.

    Read from ``/proc`` (Linux): the listening socket's inode, then the process whose file
    descriptors hold it. msctl's own routers are named as such: the router of this
    ``MSCTL_HOME``'s run (from its state file), or another ``msctl`` router (an agent's, a
    run of another home, ``msctl router``). A process of another user cannot be looked into;
    then a Zenoh probe says at least whether a router answers there.

    Returns:
        ``(who, fix)``, both phrases to put in one line.
    """
    pid = _listening_pid(port)
    if pid is None:
        if _zenoh_answers(port):
            return (
                "a Zenoh router (rmw_zenohd, `msctl router` or another msctl run)",
                "stop it, or choose another port",
            )
        return "another program", "stop it, or choose another port"
    command = _command_line(pid)
    if "msctl" not in command or "router" not in command:
        who = f"pid {pid} (`{_short(command)}`), no msctl router"
        return who, "stop it, or choose another port"
    run = _run_holding(pid)
    if run is not None:
        return run, "stop that run with `msctl down`, or use its router as it is"
    parent = _command_line(_parent_pid(pid))
    if "msctl" in parent and " agent" in parent:
        return (
            f"the router of `msctl agent` (pid {_parent_pid(pid)})",
            "stop that agent, or choose another port",
        )
    return (
        f"msctl's router pid {pid} (`{_short(command)}`)",
        "stop it (or the run or agent that started it), or choose another port",
    )


def _listening_pid(port: int) -> int | None:
    inodes = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            # local address "0100007F:1D27", state 0A = LISTEN, inode in field 9
            if len(fields) < 10 or fields[3] != "0A":
                continue
            if int(fields[1].rsplit(":", 1)[1], 16) == port:
                inodes.add(f"socket:[{fields[9]}]")
    if not inodes:
        return None
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            fds = list((proc / "fd").iterdir())
        except OSError:
            continue  # gone, or another user's
        for fd in fds:
            try:
                if os.readlink(fd) in inodes:
                    return int(proc.name)
            except OSError:
                # This descriptor closed while we looked; the process's others still count
                # (a busy process, the holder itself, opens and closes them all the time).
                continue
    return None


def _command_line(pid: int | None) -> str:
    if not pid:
        return ""
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return ""
    return raw.replace(b"\0", b" ").decode(errors="replace").strip()


def _parent_pid(pid: int) -> int | None:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    # "pid (comm) state ppid ...": comm may hold spaces and parentheses.
    return int(stat.rsplit(")", 1)[1].split()[1])


def _short(command: str, width: int = 120) -> str:
    """A command line as one would type it: ``msctl router ...`` rather than the interpreter
    and boot module that run it."""
    words = command.split()
    for index, word in enumerate(words):
        if word == "msctl" or word.endswith("/msctl"):
            words = ["msctl", *words[index + 1 :]]
            break
    command = " ".join(words)
    return command if len(command) <= width else command[: width - 3] + "..."


def _run_holding(pid: int) -> str | None:
    """The run of this MSCTL_HOME whose router is ``pid``, described, if it is one."""
    try:
        from msctl.launcher import state

        document = state.read_state()
    except Exception:  # an unreadable state file only means we cannot tell
        return None
    if not document or not state.supervisor_alive(document):
        return None
    for process in document.get("processes", []):
        if process.get("name") == "router" and process.get("pid") == pid:
            return (
                f"the router of `msctl up {document.get('template')}` running on "
                f"{document.get('host')} from {state.state_dir()} (router pid {pid}, "
                f"supervisor pid {document.get('supervisor_pid')})"
            )
    return None


def _zenoh_answers(port: int) -> bool:
    try:
        from msctl.launcher.router import router_reachable

        return router_reachable(f"tcp/127.0.0.1:{port}")
    except Exception:
        return False


# --------------------------------------------------------------------------- routers' links
#: Where a Zenoh router describes itself (locators, sessions and their links) in its admin
#: space; ``*`` asks every router reachable from the session that has one.
ROUTERS_ADMIN_KEY = "@/*/router"


@dataclass(frozen=True)
class PlainLink:
    """A link of a router that carries traffic unencrypted beyond this computer.

    Attributes:
        router: The zid of the router that reported it.
        peer: The zid of the other end.
        whatami: What the other end is (``router``, ``peer``, ``client``).
        local: The link's end at the reporting router (``tcp/10.0.0.5:7448``).
        remote: Its other end.
    """

    router: str
    peer: str
    whatami: str
    local: str
    remote: str

    def __str__(self) -> str:
        return (
            f"{self.local} <-> {self.remote} (router {self.router} to {self.whatami} {self.peer})"
        )


def plain_links(documents: list[dict]) -> list[PlainLink]:
    """The links of the routers described by ``documents`` (their admin space's
    ``@/<zid>/router``) that are neither encrypted nor within this computer.

    A link is within this computer when both its ends are loopback addresses (or it is a
    unix socket); one of a reporting router to its own non-loopback address counts as
    leaving: that address is reachable from the network.
    """
    found: list[PlainLink] = []
    seen: set[frozenset[str]] = set()  # both ends' routers report a link between them
    for document in documents:
        for session in document.get("sessions") or []:
            for link in session.get("links") or []:
                ends = [link.get("src") or "", link.get("dst") or ""]
                try:
                    parsed = [parse(end) for end in ends]
                except EndpointError:
                    continue
                if any(p.encrypted for p in parsed):
                    continue
                if all(not p.leaves_computer for p in parsed) or frozenset(ends) in seen:
                    continue
                seen.add(frozenset(ends))
                found.append(
                    PlainLink(
                        str(document.get("zid", "?")),
                        str(session.get("peer", "?")),
                        str(session.get("whatami", "?")),
                        ends[0],
                        ends[1],
                    )
                )
    return found


def router_documents(session: object, timeout: float = 1.0) -> list[dict] | None:
    """Every reachable router's own description from its admin space, or ``None`` when none
    answered (its admin space is off, or its access control denies the question).

    Args:
        session: An open Zenoh session connected to a router.
        timeout: Seconds to wait for the answers.
    """
    import json

    documents = []
    try:
        replies = session.get(ROUTERS_ADMIN_KEY, timeout=timeout)  # type: ignore[attr-defined]
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                documents.append(json.loads(reply.ok.payload.to_bytes()))
            except ValueError:
                continue
    except Exception:  # a closed session, a refused query: nothing known
        return None
    return documents or None

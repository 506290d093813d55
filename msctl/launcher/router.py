"""This computer's Zenoh router as a supervised process: whether one answers, the embedded
router's settings from the environment, starting it and waiting for it to listen."""

from __future__ import annotations

import json
import os
import socket
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from components.comm.session import SessionSettings
from msctl.errors import MsctlError
from msctl.launcher import boot
from msctl.launcher.supervisor import (
    ManagedProcess,
    ProcessState,
    Supervisor,
)

#: The router's process name in a supervisor.
ROUTER_PROCESS = "router"


def _tcp_refused(endpoint: str, timeout: float) -> bool:
    """Whether nothing accepts TCP connections on a ``tcp/HOST:PORT`` endpoint (``False``
    when it cannot tell: another protocol, a name that does not resolve)."""
    protocol, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if protocol != "tcp" or not port.isdigit():
        return False
    host = host.strip("[]")
    if host in ("", "0.0.0.0", "::"):
        host = "localhost"
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            return False
    except ConnectionRefusedError:
        return True
    except OSError:
        return False


def router_reachable(endpoint: str, timeout: float = 0.5) -> bool:
    """Whether a Zenoh router answers on ``endpoint``."""
    import zenoh

    # A closed port is known at once, while a Zenoh client keeps retrying it for the whole
    # timeout: without this, each "no router yet" cost 0.5 s of start-up.
    if _tcp_refused(endpoint, timeout):
        return False
    settings = SessionSettings(mode="client", connect=(endpoint,), listen=())
    config = settings.to_config()
    config.insert_json5("connect/timeout_ms", str(int(timeout * 1000)))
    try:
        session = zenoh.open(config)
    except Exception:
        return False
    session.close()
    return True


def listen_endpoint_for(connect_endpoint: str) -> str:
    """Where to listen so that ``connect_endpoint`` reaches us: loopback only for the
    default ``tcp/localhost:7447`` (a plain router open to every interface let anyone on
    the network command the robot); ``MSCTL_ROUTER_LISTEN`` adds endpoints on purpose."""
    if connect_endpoint.startswith("tcp/localhost:"):
        return "tcp/127.0.0.1:" + connect_endpoint.rsplit(":", 1)[1]
    return connect_endpoint


#: ``msctl router``'s exit codes after which a restart would fail the same way: 2 is its
#: :class:`~msctl.errors.InputError` (a port another process holds, an address that is not
#: this computer's, an identity missing). The router is FAILED at once, never restarted five
#: times in a minute.
ROUTER_FINAL_EXITS = {2: "its settings cannot work as they are"}


class RouterStartError(MsctlError):
    """The embedded router cannot start; the message is its own one line (what, and the fix)."""

    exit_code = 2


def _env_endpoints(variable: str, environ: Mapping[str, str]) -> tuple[str, ...]:
    return tuple(e.strip() for e in environ.get(variable, "").split(",") if e.strip())


@dataclass(frozen=True)
class EmbeddedRouter:
    """The router ``msctl up`` and ``msctl agent`` start for this computer when none answers.

    Attributes:
        endpoint: Where this computer's sessions reach it (``MSCTL_ZENOH_CONNECT``'s first).
        host: This computer (the run's host: ``msctl up --host`` too).
        whole_assembly: It serves a run of the whole assembly (``msctl up`` off-robot): with
            ``secure``, its access control lets this computer's components write every
            module's inputs. ``None``: decided by whether the host is one of the assembly's.
        secure: Mutual TLS and access control from ``msctl net`` (``MSCTL_SECURE=1``).
        listen: ``MSCTL_ROUTER_LISTEN``: more endpoints to listen on (secure: TLS ones, in
            place of the generated TLS listener).
        connect: ``MSCTL_ROUTER_CONNECT``: routers to link to (secure: TLS ones, in place of
            the links the assembly gives).
    """

    endpoint: str
    host: str
    whole_assembly: bool | None = None
    secure: bool = False
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()

    @classmethod
    def from_env(
        cls,
        endpoint: str,
        host: str | None = None,
        whole_assembly: bool | None = None,
        environ: Mapping[str, str] | None = None,
    ) -> EmbeddedRouter:
        """The router for ``endpoint`` as the environment sets it up (see the attributes)."""
        from msctl.launcher.plan import this_host

        env = os.environ if environ is None else environ
        return cls(
            endpoint,
            host or this_host(),
            whole_assembly,
            env.get("MSCTL_SECURE") == "1",
            _env_endpoints("MSCTL_ROUTER_LISTEN", env),
            _env_endpoints("MSCTL_ROUTER_CONNECT", env),
        )

    def plain_listen(self) -> list[str]:
        """A plain router's listeners: loopback where ``endpoint`` reaches it, and each of
        ``MSCTL_ROUTER_LISTEN``. One of those that covers the loopback one (the same port on
        a wildcard address, ``tcp/0.0.0.0:7447``) replaces it: one process cannot bind both,
        and the wildcard takes loopback connections too."""
        from msctl.net.endpoints import covers

        local = listen_endpoint_for(self.endpoint)
        extra = list(dict.fromkeys(self.listen))
        if local in extra or any(covers(e, local) for e in extra):
            return extra
        return [local, *extra]

    def argv(self) -> list[str]:
        """``msctl router``'s arguments."""
        if self.secure:
            argv = ["router", "--secure", "--host", self.host]
            if self.whole_assembly is not None:
                argv.append("--whole-assembly" if self.whole_assembly else "--own-part")
        else:
            argv = ["router"]
            for endpoint in self.plain_listen():
                argv += ["--listen", endpoint]
        for endpoint in self.listen if self.secure else ():
            argv += ["--listen", endpoint]
        for endpoint in self.connect:
            argv += ["--connect", endpoint]
        return argv

    def not_applied(self) -> str:
        """What the operator asked of this router that a router already answering on
        ``endpoint`` (used as it is) does not do, as a warning line, or ``""``."""
        asked = [
            name
            for name, given in (
                ("MSCTL_SECURE", self.secure),
                ("MSCTL_ROUTER_LISTEN", self.listen),
                ("MSCTL_ROUTER_CONNECT", self.connect),
            )
            if given
        ]
        if not asked:
            return ""
        return (
            f"warning: a router already answers on {self.endpoint} and is used as it is: "
            f"{', '.join(asked)} apply only to a router msctl starts; stop that one first "
            "(`msctl down`, or the agent or router holding it) to have them"
        )

    def check(self) -> list[str]:
        """What would make the router fail at once, raised now; what to warn of, returned.

        Runs in the process that starts the router, so a setting that cannot work fails in
        well under a second with its one line (the endpoint or identity, and the fix), and
        a detached ``msctl up`` says it before it detaches. The secure config is generated
        here as the router will generate it (an identity is made for a computer running the
        whole assembly, once).

        Returns:
            Lines for the operator: a plain router open beyond this computer, an identity
            made.

        Raises:
            RouterStartError: Naming the endpoint, file or host at fault, and the fix.
        """
        from components.assembly import AssemblyError
        from msctl.commands.router import plain_exposure
        from msctl.net import config as netconfig
        from msctl.net import endpoints, pki

        notes: list[str] = []
        listen: list[tuple[str, str]]  # (endpoint, the setting it comes from)
        try:
            if self.secure:
                path, notes = netconfig.this_computer_router(
                    self.host,
                    self.whole_assembly,
                    listen=self.listen,
                    connect=self.connect or None,
                )
                document = json.loads(path.read_text())
                listen = [
                    (e, "MSCTL_ZENOH_CONNECT" if e.startswith("tcp/") else "MSCTL_NET_TLS_PORT")
                    for e in document["listen"]["endpoints"]
                ]
            else:
                for variable, given in (
                    ("MSCTL_ROUTER_LISTEN", self.listen),
                    ("MSCTL_ROUTER_CONNECT", self.connect),
                ):
                    for text in given:
                        try:
                            endpoints.parse(text)
                        except endpoints.EndpointError as exc:
                            raise endpoints.EndpointError(f"{variable}: {exc}") from None
                local = listen_endpoint_for(self.endpoint)
                listen = [
                    (e, "MSCTL_ZENOH_CONNECT" if e == local else "MSCTL_ROUTER_LISTEN")
                    for e in self.plain_listen()
                ]
                warning = plain_exposure(self.plain_listen(), self.connect)
                if warning:
                    notes.append(f"warning: {warning}")
            for text, setting in listen:
                endpoints.check_listen(text, setting)
        except endpoints.EndpointError as exc:
            raise RouterStartError(f"this computer's router: {exc}") from None
        except (AssemblyError, netconfig.NetConfigError, pki.PkiError) as exc:
            raise RouterStartError(f"this computer's secure router (--secure): {exc}") from None
        return notes


def router_argv(connect_endpoint: str) -> list[str]:
    """``msctl router``'s arguments for the embedded router, as the environment sets it up
    (see :class:`EmbeddedRouter`)."""
    return EmbeddedRouter.from_env(connect_endpoint).argv()


def start_router(
    supervisor: Supervisor,
    endpoint: str | EmbeddedRouter,
    say: Callable[[str], None] | None = None,
) -> ManagedProcess:
    """Start an embedded router (``msctl router``) as a supervised process.

    Its settings are checked first (:meth:`EmbeddedRouter.check`): one that cannot work
    raises here, and one that fails the router anyway later makes it FAILED at once
    (:data:`ROUTER_FINAL_EXITS`), not restarted.

    Args:
        supervisor: Who supervises it.
        endpoint: The router, or where this computer's sessions reach it (its settings then
            come from the environment).
        say: Where the check's warnings go (a plain router open beyond this computer).

    Raises:
        RouterStartError: A setting that cannot work (named, with the fix).
    """
    router = endpoint if isinstance(endpoint, EmbeddedRouter) else EmbeddedRouter.from_env(endpoint)
    for line in router.check():
        if say is not None:
            say(line)
    process = supervisor.add(
        ROUTER_PROCESS,
        boot.argv("msctl", *router.argv()),
        final_exits=ROUTER_FINAL_EXITS,
    )
    # Stopped while it still starts, it ends quietly (msctl.launcher.boot).
    with boot.held_sigint():
        supervisor.start(process.name)
    return process


def router_error_line(router: ManagedProcess) -> str:
    """The router's own last error line, whole (``last_error`` keeps only its tail)."""
    for line in reversed(list(router.log.tail)):
        text = line.strip()
        if text.startswith("error:"):
            return text.removeprefix("error:").strip()
    return router.last_error or "no answer"


def wait_for_router(
    supervisor: Supervisor,
    router: ManagedProcess,
    endpoint: str,
    timeout: float = 30.0,  # a loaded machine starts a (secure) router in 10+ s
    stopping: Callable[[], bool] | None = None,
) -> bool:
    """Wait until the embedded router answers on ``endpoint``; mark it running.

    Args:
        supervisor: The supervisor that started it.
        router: Its process.
        endpoint: Where it listens.
        timeout: Seconds to wait for it.
        stopping: Polled while waiting: once it says so, stop waiting (a Ctrl-C during
            start-up must not wait for a router that is about to be stopped anyway).

    Returns:
        Whether it answers (``False``: ``stopping`` said to stop first).

    Raises:
        RuntimeError: If it failed or did not answer within ``timeout`` (with its last error).
    """
    deadline = time.monotonic() + timeout
    while not router_reachable(endpoint):
        if stopping is not None and stopping():
            return False
        with boot.held_sigint():  # it may restart the router
            supervisor.poll()
        if router.state is ProcessState.FAILED and router.restarts == 0:
            # It said why in one line, and a restart would say it again.
            raise RouterStartError(f"the embedded router cannot start: {router_error_line(router)}")
        if router.state is ProcessState.FAILED or time.monotonic() > deadline:
            raise RuntimeError(
                f"the embedded router could not listen on {endpoint}: "
                f"{router.last_error or 'no answer'}"
            )
        time.sleep(0.02)
    supervisor.mark_running(ROUTER_PROCESS)
    return True

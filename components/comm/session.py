"""Opening Zenoh sessions, from one place.

Every msctl process opens its session here so that mode, endpoints, scouting and lease are
the same everywhere and can be changed without touching code. Defaults mirror rmw_zenoh's:
a *peer* that connects to the router on ``tcp/localhost:7447`` and listens on loopback for
direct links to the other processes of the same computer; multicast scouting off.

Settings, lowest to highest precedence: built-in defaults, the json5 file named by
``MSCTL_ZENOH_CONFIG`` (any Zenoh config; our settings are applied on top), environment
variables, explicit arguments.

Environment variables:
    MSCTL_ZENOH_CONFIG     path of a json5 Zenoh configuration to start from
    MSCTL_ZENOH_MODE       ``peer`` (default), ``client`` or ``router``; commands, scripts
                           and launched components are clients unless it is set
    MSCTL_ZENOH_CONNECT    comma-separated endpoints to connect to (default tcp/localhost:7447)
    MSCTL_ZENOH_LISTEN     comma-separated endpoints to listen on (peer default tcp/127.0.0.1:0)
    MSCTL_ZENOH_MULTICAST  ``1`` to enable multicast scouting (default off)
    MSCTL_ZENOH_LEASE_MS   link lease in ms (default 1000: a frozen peer is noticed in ~1 s)
    MSCTL_IDENTITY         connect with this fleet identity (``msctl net``): an operator
                           name (``alice@ground1``) or a host name; the session becomes a
                           mutual-TLS client of ``tls/localhost:7448`` unless
                           MSCTL_ZENOH_CONNECT says where
    ROS_DOMAIN_ID          ROS domain, the first chunk of every key (default 0)
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from types import MappingProxyType
from typing import Any, NamedTuple

from components.errors import ConfigError

#: Where rmw_zenoh's router (``rmw_zenohd``) listens, and so where ours does by default.
DEFAULT_ROUTER_PORT = 7447
DEFAULT_CONNECT = (f"tcp/localhost:{DEFAULT_ROUTER_PORT}",)
DEFAULT_ROUTER_LISTEN = (f"tcp/[::]:{DEFAULT_ROUTER_PORT}",)
#: Where a secured router (``msctl net config``) takes other computers, over mutual TLS.
SECURE_ROUTER_PORT = 7448
# Zenoh's default lease is 10 s: a frozen peer would keep its tokens (and its place in the
# graph) for ten seconds. 1 s with 4 keep-alives per lease notices it in about a second
# while tolerating a couple of lost Wi-Fi frames.
DEFAULT_LEASE_MS = 1000
KEEP_ALIVES_PER_LEASE = 4


class SessionConfigError(ConfigError):
    """A session setting (environment variable or file) that cannot be used.

    A :class:`~components.errors.ConfigError`: session settings come from
    ``MSCTL_ZENOH_*`` in the environment, whichever command reads them: the operator's
    input (exit 2), not our bug.
    """


class SessionOpenError(SessionConfigError):
    """Zenoh refused to open a session with usable settings (e.g. a client reaching no router)."""


class SessionSettings(NamedTuple):
    """How to open a Zenoh session.

    Attributes:
        mode: ``peer``, ``client`` or ``router``.
        connect: Endpoints to connect to.
        listen: Endpoints to listen on (empty: Zenoh's default for the mode).
        multicast: Multicast scouting on or off.
        lease_ms: Link lease in milliseconds.
        domain: ROS domain id.
        config_file: A json5 Zenoh config to start from.
        extra: More Zenoh settings as ``{"path/in/config": value}``, applied last.
    """

    mode: str = "peer"
    connect: tuple[str, ...] = DEFAULT_CONNECT
    listen: tuple[str, ...] = ("tcp/127.0.0.1:0",)
    multicast: bool = False
    lease_ms: int = DEFAULT_LEASE_MS
    domain: int = 0
    config_file: Path | None = None
    # Shared by every default instance, so read-only; ``_replace`` gives a new one.
    extra: Mapping[str, Any] = MappingProxyType({})

    @classmethod
    def from_env(cls, environ: dict[str, str] | None = None, **overrides: Any) -> SessionSettings:
        """Defaults, then environment variables, then ``overrides``.

        Raises:
            SessionConfigError: If a variable holds a value that cannot be used.
        """
        env = os.environ if environ is None else environ
        settings = cls()
        changes: dict[str, Any] = {}
        if value := env.get("MSCTL_ZENOH_CONFIG"):
            path = Path(value)
            if not path.is_file():
                raise SessionConfigError(
                    f"MSCTL_ZENOH_CONFIG names {path}, which is not a file; "
                    "fix the path or unset it"
                )
            changes["config_file"] = path
        if value := env.get("MSCTL_ZENOH_MODE"):
            changes["mode"] = value
        if value := env.get("MSCTL_ZENOH_CONNECT"):
            changes["connect"] = _endpoints(value, "MSCTL_ZENOH_CONNECT")
        if value := env.get("MSCTL_ZENOH_LISTEN"):
            changes["listen"] = _endpoints(value, "MSCTL_ZENOH_LISTEN")
        if value := env.get("MSCTL_ZENOH_MULTICAST"):
            changes["multicast"] = _boolean(value, "MSCTL_ZENOH_MULTICAST")
        if value := env.get("MSCTL_ZENOH_LEASE_MS"):
            changes["lease_ms"] = _integer(value, "MSCTL_ZENOH_LEASE_MS", minimum=100)
        if value := env.get("ROS_DOMAIN_ID"):
            changes["domain"] = _integer(value, "ROS_DOMAIN_ID", minimum=0)
        # A router serves with its own config (``msctl router --secure``), never as a client.
        if (value := env.get("MSCTL_IDENTITY")) and overrides.get("mode") != "router":
            changes["mode"] = "client"  # a secured router's ACL must see every message
            changes["listen"] = ()
            changes["extra"] = {"transport/link/tls": identity_tls(value)}
            if not env.get("MSCTL_ZENOH_CONNECT"):
                changes["connect"] = (f"tls/localhost:{SECURE_ROUTER_PORT}",)
        changes.update({k: v for k, v in overrides.items() if v is not None})
        settings = settings._replace(**changes)
        settings.validate()
        return settings

    @classmethod
    def joining(cls, environ: dict[str, str] | None = None) -> SessionSettings:
        """Settings of a process that joins a running assembly from outside it: a command,
        a script (``connect()``), an operator's tool. A client of the router, unless
        ``MSCTL_ZENOH_MODE`` says otherwise.

        The router holds every token and route of the assembly and answers a client whole,
        at once. A peer joining later learns the graph over the direct links it manages to
        open, and measured on two_dragons (53 peers) it knew 0-625 of the 625 tokens a
        client saw, from one query to the next. It is what rmw_zenoh advises for a tool
        beside running nodes (rviz as a client).

        Raises:
            SessionConfigError: If a variable holds a value that cannot be used.
        """
        env = os.environ if environ is None else environ
        if env.get("MSCTL_ZENOH_MODE"):
            return cls.from_env(env)
        settings = cls.from_env(env, mode="client")
        return settings._replace(listen=()) if settings.mode == "client" else settings

    @classmethod
    def launched(cls, environ: dict[str, str] | None = None) -> SessionSettings:
        """Settings of a component process a launcher started (``msctl up``'s workers, here
        or through a computer's agent): a client of its computer's router, as a joining tool
        is (:meth:`joining`), unless ``MSCTL_ZENOH_MODE`` says otherwise.

        As peers, the 23 processes of two_dragons each linked to every other (253 links,
        each with its handshake, declarations and tokens): measured against clients of the
        router on this 2-core machine, starting took 5.7-6.3 CPU-seconds (clients:
        3.2-3.9), the assembly at rest 1.1 cores (0.8-0.9), and the e-stop's p99 42-55 ms
        (24-30 ms). A sample takes one hop more, through the router (Rust, at once).

        Raises:
            SessionConfigError: If a variable holds a value that cannot be used.
        """
        return cls.joining(environ)

    def validate(self) -> None:
        """Check the settings.

        Raises:
            SessionConfigError: With the setting at fault and what to use instead.
        """
        if self.mode not in ("peer", "client", "router"):
            raise SessionConfigError(
                f"Zenoh mode {self.mode!r} is not one of peer, client, router (MSCTL_ZENOH_MODE)"
            )
        if self.mode == "client" and not self.connect:
            raise SessionConfigError("a client session needs at least one endpoint to connect to")
        for endpoint in (*self.connect, *self.listen):
            if "/" not in endpoint:
                raise SessionConfigError(
                    f"endpoint {endpoint!r} lacks a protocol; write it like tcp/127.0.0.1:7447"
                )

    def with_endpoint(self, endpoint: str) -> SessionSettings:
        """The same settings connecting to exactly ``endpoint`` (tests, ``--router``)."""
        return self._replace(connect=(endpoint,))

    def to_config(self) -> Any:
        """A ``zenoh.Config`` for these settings."""
        import zenoh

        if self.config_file is not None:
            try:
                config = zenoh.Config.from_file(str(self.config_file))
            except Exception as exc:
                raise SessionConfigError(
                    f"cannot read Zenoh config {self.config_file}: {exc}"
                ) from exc
        else:
            config = zenoh.Config()
        values: dict[str, Any] = {
            "mode": self.mode,
            "connect/endpoints": list(self.connect),
            "scouting/multicast/enabled": self.multicast,
            "transport/link/tx/lease": self.lease_ms,
            "transport/link/tx/keep_alive": KEEP_ALIVES_PER_LEASE,
            # Latched topics use Zenoh's advanced publisher, which orders its cache by
            # timestamp; rmw_zenoh turns timestamping on for the same reason.
            "timestamping/enabled": True,
            "connect/retry": RECONNECT,
        }
        if self.listen:
            values["listen/endpoints"] = list(self.listen)
        if self.mode != "client":
            # A peer that cannot reach the router still runs (and works with the peers it
            # can reach); it keeps retrying in the background, as rmw_zenoh's peers do.
            values["connect/exit_on_failure"] = False
        values.update(self.extra)
        for path, value in values.items():
            try:
                config.insert_json5(path, json.dumps(value))
            except Exception as exc:
                raise SessionConfigError(f"Zenoh rejected {path}={value!r}: {exc}") from exc
        return config


#: How often a lost link is tried again (``connect/retry``), for sessions and routers alike.
#: Zenoh's default starts after 1 s and backs off to 4 s: after a radio outage the routers
#: then stay apart up to 4 s longer than the outage, and a restarted router is not reached
#: within a second. A try is a TCP SYN (and, once answered, the handshake): on a link that
#: is down, a few bytes a second.
RECONNECT: dict[str, Any] = {
    "period_init_ms": 100,
    "period_max_ms": 1000,
    "period_increase_factor": 1.5,
}


def identity_tls(name: str) -> dict[str, Any]:
    """The mutual-TLS settings of fleet identity ``name`` (see ``msctl net``).

    ``name`` is a host (its CN) or an operator (``alice@ground1``, CN ``operator:...``).

    Raises:
        SessionConfigError: If ``msctl net`` made no such identity here.
    """
    from components.assembly import state_dir

    net = state_dir() / "net"
    for common_name in (name, f"operator:{name}"):
        folder = net / "identities" / common_name.replace(":", "-")
        if (folder / "cert.pem").is_file() and (folder / "key.pem").is_file():
            mode = (folder / "key.pem").stat().st_mode & 0o777
            if mode & 0o077:
                # `MSCTL_HOME/net` is copied between computers, and a copy can lose modes.
                raise SessionConfigError(
                    f"MSCTL_IDENTITY={name!r}: private key {folder / 'key.pem'} is open to "
                    f"others (mode {mode:04o}): run `chmod 600 {folder / 'key.pem'}`"
                )
            return {
                "root_ca_certificate": str(net / "ca" / "ca.pem"),
                "connect_certificate": str(folder / "cert.pem"),
                "connect_private_key": str(folder / "key.pem"),
                "enable_mtls": True,
            }
    raise SessionConfigError(
        f"MSCTL_IDENTITY={name!r}: no such identity in {net / 'identities'}; run "
        f"`msctl net add-operator {name}` (or `msctl net show` for the known ones)"
    )


def zenoh_reason(exc: BaseException) -> str:
    """A Zenoh error's message without the Rust source location it ends with
    (``... at /root/.cargo/.../orchestrator.rs:447.``): a line for the operator, not us."""
    import re

    text = re.sub(r"\s+at\s+\S+\.rs:\d+(:\d+)?\.?", "", str(exc)).strip()
    return text.rstrip("!").strip() or type(exc).__name__


def _endpoints(text: str, variable: str) -> tuple[str, ...]:
    endpoints = tuple(e.strip() for e in text.split(",") if e.strip())
    if not endpoints:
        raise SessionConfigError(f"{variable} is set but names no endpoint")
    for endpoint in endpoints:
        if "/" not in endpoint:
            raise SessionConfigError(
                f"{variable}: endpoint {endpoint!r} lacks a protocol; "
                "write it like tcp/127.0.0.1:7447"
            )
    return endpoints


def _boolean(text: str, variable: str) -> bool:
    value = text.strip().lower()
    if value in ("1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise SessionConfigError(f"{variable}={text!r} is not one of 1/0, true/false, yes/no, on/off")


def _integer(text: str, variable: str, minimum: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise SessionConfigError(f"{variable}={text!r} is not a whole number") from None
    if value < minimum:
        raise SessionConfigError(f"{variable}={value} is below {minimum}")
    return value


def open_session(settings: SessionSettings | None = None) -> Any:
    """Open a Zenoh session. Close it explicitly (``with`` or ``close()``): a session with a
    Python callback subscriber that is left open hangs interpreter exit.

    Raises:
        SessionConfigError: If the settings are unusable.
        SessionOpenError: If Zenoh refuses to open (a client that reaches no router).
    """
    import zenoh

    settings = settings or SessionSettings.from_env()
    config = settings.to_config()
    try:
        session = zenoh.open(config)
    except Exception as exc:
        raise SessionOpenError(
            f"cannot open a Zenoh {settings.mode} session (connect {list(settings.connect)}, "
            f"listen {list(settings.listen)}): {zenoh_reason(exc)}"
        ) from exc
    if settings.mode in ("peer", "client") and settings.connect:
        # Forget the sessions closed since (a script may open and close many in its life).
        for zid, known in list(_QUESTION_ROUTES.items()):
            if known.session.is_closed():
                _QUESTION_ROUTES.pop(zid, None)  # another thread may have pruned it already
        _QUESTION_ROUTES[str(session.zid())] = _QuestionRoute(
            session, settings._replace(mode="client", listen=()), settings.mode == "peer"
        )
    return session


class _QuestionRoute:
    """How one open session of this process asks graph questions (see
    :func:`graph_questions`).

    Attributes:
        session: The session.
        client: Settings of a client of the same router(s).
        through_client: Whether its questions go through such a client: a peer's always, a
            client's once it follows tokens (:func:`ask_through_a_client`).
    """

    __slots__ = ("client", "session", "through_client")

    def __init__(self, session: Any, client: SessionSettings, through_client: bool) -> None:
        self.session, self.client, self.through_client = session, client, through_client


#: Each open session of this process that connects to a router, by Zenoh id.
_QUESTION_ROUTES: dict[str, _QuestionRoute] = {}


def ask_through_a_client(session: Any) -> None:
    """From now on, ``session``'s graph questions go through a client of its router (see
    :func:`graph_questions`); :func:`~components.comm.liveliness.follow_tokens` calls it
    before declaring a liveliness subscriber."""
    route = _QUESTION_ROUTES.get(str(session.zid()))
    if route is not None:
        route.through_client = True


@contextmanager
def graph_questions(session: Any) -> Iterator[Any]:
    """The session to ask one-shot graph questions (liveliness queries) of ``session``'s
    network: ``session`` itself, or a client of its router, opened for the question and
    closed after, for a peer or for a session that follows tokens.

    Zenoh 1.10 answers part of the tokens to either:

    * a peer: measured, 0 to 100 of 100 tokens from one query to the next, even for the
      peer's own tokens, where a client of the same router got all 100 every time (a client
      opens in 1-4 ms);
    * a client with a liveliness subscriber (every component and command that subscribes
      follows its topics' publisher tokens): the router ends the query (its DeclareFinal)
      before it has sent again the tokens it already sent that client for the subscriber,
      which then no longer count as answers. Measured on a loaded machine: 3 of 20 `msctl
      topic echo` error paths got 100 of 159 tokens, not one publisher among them; Zenoh's
      trace showed 100 tokens, the final, then the other 59. A client with no liveliness
      subscriber got them all every time.

    A session that cannot open a client (its router is down) asks through itself: part of
    the answer rather than none.
    """
    route = _QUESTION_ROUTES.get(str(session.zid()))
    asked = None
    if route is not None and route.through_client:
        try:
            asked = open_session(route.client)
        except (SessionOpenError, SessionConfigError):
            asked = None
    try:
        yield session if asked is None else asked
    finally:
        if asked is not None:
            asked.close()


def router_settings(
    listen: tuple[str, ...] = DEFAULT_ROUTER_LISTEN, **overrides: Any
) -> SessionSettings:
    """Settings for a router like rmw_zenoh's ``rmw_zenohd``: listens, connects to nobody.

    It opens at once: Zenoh's ``scouting/delay`` (0.5 s of waiting in ``open`` for first
    links) buys a router nothing, and a restarted router must carry data again quickly.
    """
    base = SessionSettings.from_env(mode="router")
    extra = {"scouting/delay": 0, **base.extra, **overrides.pop("extra", {})}
    return base._replace(mode="router", listen=tuple(listen), connect=(), extra=extra, **overrides)

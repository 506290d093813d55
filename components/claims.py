"""Claims: who drives which module, as liveliness tokens on the data plane.

Before commanding a module an operator claims it. A claim is a Zenoh liveliness token naming
the module, the operator (``user@host``) and the node that will send the commands, so it
vanishes by itself when the operator's process dies or its link drops (within the session
lease, about a second). Joint managers, the kinematics manager and the steering operator
take commands for a claimed module only from the holder's node (identified by the GID of
each sample against the graph's publisher tokens; see :meth:`Subscription.allow
<components.comm.topics.Subscription.allow>`). A halt is never blocked by a claim.

API summary::

    from components.claims import Claims, ClaimRefused, default_holder

    claims = Claims(session, domain=0, modules=["limb1", "wheel1"])  # watches every claim
    claims.holders()            # {"limb1": ClaimInfo(module, holder, node, since, ...)}
    claims.survey()             # every live claim on the network now (msctl claims)
    claims.on_change(cb)        # cb(module, holder_or_None), on a Zenoh thread
    try:
        claim = claims.claim("limb1", default_holder(), node)      # node: a comm.Node
    except ClaimRefused as exc:  # held by someone else: exc.holder names who, since when
        claim = claims.claim("limb1", default_holder(), node, take=True)
    claim.lost                  # threading.Event, set the moment another operator takes it
    claim.on_lost(cb)           # cb(new_holder: ClaimInfo), on a Zenoh thread
    claim.release()             # idempotent; also done by claims.close()
    claims.close()              # releases this object's claims, stops watching

Enforcement (robot side, :mod:`components.claim_guard`): an interface's ``Subscribe``
carrying a ``ClaimRule`` (set on every input whose declared role is a command by the
builder's :func:`components.roles.bind`, with :func:`components.roles.command_rule`) is kept
by the executor's ``ClaimGuard`` on the module's holder; other senders are refused, counted
under ``not_holder`` (or ``unclaimed`` when the template says ``claims = "required"``), and
warned about once naming the holder.

Who holds a module, when several tokens name it: the newest claim (largest ``since``). A
take-over is stamped just after the claim it takes (even across skewed clocks), so it always
wins; a claim without ``take`` is refused while the module is held. Two claims made at the
same moment on a free module both succeed locally, and the older is then lost (its
``lost`` event is set, as for a take-over): everyone watching computes the same holder from
the same tokens. A claim that is lost is released by its own side.

Token key (ours, beside rmw_zenoh's ``@ros2_lv`` graph, which ROS tools would not parse)::

    @msctl/claim/<domain>/<module>/<since ns>/<holder, %-quoted>/<session zid>/<node, / as %>
"""

from __future__ import annotations

import getpass
import logging
import os
import re
import socket
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from datetime import datetime
from typing import Any
from urllib.parse import quote, unquote

from components.comm.liveliness import ask_tokens, follow_tokens
from components.comm.names import mangle, unmangle
from components.errors import ConfigError

_log = logging.getLogger(__name__)


#: The first chunks of every claim token (a verbatim ``@`` chunk: wildcards never match it,
#: so only claim watchers see these tokens).
PREFIX = "@msctl/claim"
#: Seconds :meth:`Claims.claim` waits for the network's current claims of a module.
QUERY_TIMEOUT = 2.0
#: Seconds a claim waits for its session to reach a router or peer before asking who holds
#: the module: asked unlinked, the network's answer is "nobody", and the claim would be
#: granted over a holder it never heard of.
LINK_TIMEOUT = 10.0
#: Seconds after a Claims object is made during which "nobody holds it" is asked again
#: before it is believed: a session linked a moment ago may not have every peer's
#: declarations yet (measured: the first liveliness query after open missed a live token
#: in about one try in three, a query 10 ms later never did).
SETTLE = 1.0

_MODULE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_NS = 1_000_000_000


class ClaimError(ConfigError):
    """A claim that cannot be made; the message says why and what to do."""


class UnknownModuleError(ClaimError, LookupError):
    """A claim for a module the assembly does not have; the message names those it has."""


class ClaimRefused(ClaimError):
    """The module is held by another operator and ``take`` was not asked.

    Attributes:
        holder: The claim that holds the module (who, which node, since when).
    """

    def __init__(self, holder: ClaimInfo) -> None:
        super().__init__(
            f"module {holder.module} is claimed by {holder.holder} (node {holder.node}) "
            f"since {holder.since_text()}; take it over with take=True "
            "(msctl teleop --take), or ask them to release it"
        )
        self.holder = holder


@dataclass(frozen=True)
class ClaimInfo:
    """One claim as its token tells it.

    Attributes:
        module: The claimed module's slot (``limb1``).
        holder: The operator, ``user@host``.
        node: Fully qualified node that sends the commands (``/ground1/teleop``).
        since: When the claim was made (wall clock, seconds since the epoch).
        zid: Zenoh session id of the node (two nodes of one name are told apart by it).
        key: The token's key expression.
    """

    module: str
    holder: str
    node: str
    since: float
    zid: str
    key: str

    @property
    def since_ns(self) -> int:
        """``since`` in integer nanoseconds, as the token carries it (the ordering key)."""
        return int(self.key.split("/")[4])

    def since_text(self) -> str:
        """``since`` as local time of day (and date when not today), for messages."""
        moment = datetime.fromtimestamp(self.since)
        if moment.date() == datetime.now().date():
            return moment.strftime("%H:%M:%S")
        return moment.strftime("%Y-%m-%d %H:%M:%S")

    def order(self) -> tuple[int, str, str, str]:
        """Sort key: the largest holds the module (ties broken by name, deterministically)."""
        return (self.since_ns, self.holder, self.node, self.zid)

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready view (``msctl claims --json``)."""
        return {
            "module": self.module,
            "holder": self.holder,
            "node": self.node,
            "since": self.since,
            "zid": self.zid,
        }


def claim_key(domain: int, module: str, since_ns: int, holder: str, zid: str, node: str) -> str:
    """The liveliness key of one claim."""
    return "/".join(
        (PREFIX, str(domain), module, str(since_ns), quote(holder, safe="@.-_+"), zid, mangle(node))
    )


def parse_claim(key: str) -> ClaimInfo | None:
    """The claim a token key carries, or ``None`` if it is not a well-formed claim token."""
    parts = str(key).split("/")
    if len(parts) != 8 or "/".join(parts[:2]) != PREFIX:
        return None
    _domain, module, since_ns, holder, zid, node = parts[2:]
    if not since_ns.isdigit() or not _MODULE.match(module):
        return None
    return ClaimInfo(
        module=module,
        holder=unquote(holder),
        node=unmangle(node),
        since=int(since_ns) / _NS,
        zid=zid,
        key=str(key),
    )


def default_holder() -> str:
    """This operator as a claim names it: ``user@host`` (host from ``MSCTL_HOST`` if set)."""
    try:
        user = getpass.getuser()
    except Exception:  # no user name in a bare container
        user = str(os.getuid())
    return f"{user}@{os.environ.get('MSCTL_HOST') or socket.gethostname()}"


def holder_of(claims: Iterable[ClaimInfo]) -> ClaimInfo | None:
    """Who holds a module among its claims: the newest (``None`` if there is none)."""
    return max(claims, key=ClaimInfo.order, default=None)


class Claim:
    """A claim this process holds. Made by :meth:`Claims.claim`.

    Attributes:
        info: The claim as its token tells it.
        lost: Set once another operator took the module over (or won a same-moment race);
            the claim is then released already, and :attr:`lost_to` names the new holder.
        lost_to: The claim that took this one's place, once :attr:`lost` is set.
    """

    def __init__(self, owner: Claims, info: ClaimInfo, token: Any) -> None:
        self._owner = owner
        self.info = info
        self._token = token
        self.lost = threading.Event()
        self.lost_to: ClaimInfo | None = None
        self._callbacks: list[Callable[[ClaimInfo], None]] = []
        self._lock = threading.Lock()
        self._released = False

    @property
    def module(self) -> str:
        """The claimed module."""
        return self.info.module

    @property
    def held(self) -> bool:
        """Still held: neither released nor lost."""
        return not (self._released or self.lost.is_set())

    def on_lost(self, callback: Callable[[ClaimInfo], None]) -> None:
        """Call ``callback(new_holder)`` when this claim is lost (at once if it already is).

        It runs on a Zenoh thread: a textual app hands it to the UI with
        ``call_from_thread`` / ``post_message``. An exception in it is swallowed after
        being printed to the log, so it never breaks the watcher.
        """
        with self._lock:
            if self.lost_to is None:
                self._callbacks.append(callback)
                return
            new_holder = self.lost_to
        _call(callback, new_holder)

    def _lose(self, new_holder: ClaimInfo) -> None:
        with self._lock:
            if self.lost_to is not None or self._released:
                return
            self.lost_to = new_holder
            callbacks = list(self._callbacks)
        # Lost before released: whoever sees the claim no longer held (releasing undeclares
        # the token, a network call) must find it lost, and to whom, not merely gone.
        self.lost.set()
        self.release()
        for callback in callbacks:
            _call(callback, new_holder)

    def release(self) -> None:
        """Give the module up: the token is undeclared (idempotent)."""
        with self._lock:
            if self._released:
                return
            self._released = True
        self._owner._forget(self)
        try:
            self._token.undeclare()
        except Exception as exc:  # the session may be closed already: the token went with it
            _log.debug("claim of %s: token not undeclared: %s", self.info.module, exc)

    def __enter__(self) -> Claim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __repr__(self) -> str:
        state = "lost" if self.lost.is_set() else "held" if self.held else "released"
        return f"<Claim {self.module} by {self.info.holder} ({self.info.node}), {state}>"


class Claims:
    """Watches every claim of a domain, and makes this process's claims.

    Args:
        session: An open Zenoh session (the caller keeps ownership; close this first).
        domain: ROS domain id.
        modules: The assembly's modules; with them, a claim for another name is refused
            naming these. ``None``: any well-formed name may be claimed.
    """

    def __init__(self, session: Any, domain: int = 0, modules: Iterable[str] | None = None) -> None:
        self.session = session
        self.domain = domain
        self.modules: tuple[str, ...] | None = None if modules is None else tuple(modules)
        self._lock = threading.Lock()
        self._tokens: dict[str, ClaimInfo] = {}  # key -> claim, every live claim token
        self._holders: dict[str, ClaimInfo] = {}  # module -> its holder
        self._mine: dict[str, Claim] = {}  # key -> a claim this object made
        self._callbacks: list[Callable[[str, ClaimInfo | None], None]] = []
        self._closed = False
        self._made = time.monotonic()
        self._subscriber = follow_tokens(session, f"{PREFIX}/{domain}/**", self._on_token)

    # ------------------------------------------------------------------ watching
    def holders(self) -> dict[str, ClaimInfo]:
        """Module -> the claim holding it, for every claimed module (a snapshot)."""
        with self._lock:
            return dict(self._holders)

    def holder(self, module: str) -> ClaimInfo | None:
        """The claim holding ``module``, or ``None`` if it is free."""
        with self._lock:
            return self._holders.get(module)

    def claims(self) -> list[ClaimInfo]:
        """Every live claim token, holders and losers alike, oldest first."""
        with self._lock:
            return sorted(self._tokens.values(), key=ClaimInfo.order)

    def on_change(self, callback: Callable[[str, ClaimInfo | None], None]) -> None:
        """Call ``callback(module, holder_or_None)`` whenever a module's holder changes.

        It is called at once for every module already claimed. It runs on a Zenoh thread
        (see :meth:`Claim.on_lost`); exceptions are logged and swallowed.
        """
        with self._lock:
            self._callbacks.append(callback)
            current = dict(self._holders)
        for module, holder in current.items():
            _call(callback, module, holder)

    def _on_token(self, sample: Any) -> None:
        import zenoh

        info = parse_claim(str(sample.key_expr))
        if info is None:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._tokens[info.key] = info
            else:
                self._tokens.pop(info.key, None)
            changed = self._recompute(info.module)
        self._announce(changed)

    def _recompute(self, module: str) -> list[tuple[str, ClaimInfo | None, list[Claim]]]:
        """Under the lock: the module's holder anew; what to announce if it changed."""
        new = holder_of(c for c in self._tokens.values() if c.module == module)
        old = self._holders.get(module)
        if new == old:
            return []
        if new is None:
            del self._holders[module]
        else:
            self._holders[module] = new
        losers = []
        if new is not None:
            losers = [c for key, c in self._mine.items() if c.module == module and key != new.key]
        return [(module, new, losers)]

    def _announce(self, changed: list[tuple[str, ClaimInfo | None, list[Claim]]]) -> None:
        for module, holder, losers in changed:
            if holder is not None:
                for claim in losers:
                    claim._lose(holder)
            with self._lock:
                callbacks = list(self._callbacks)
            for callback in callbacks:
                _call(callback, module, holder)

    # ------------------------------------------------------------------ claiming
    def current(self, module: str, timeout: float = QUERY_TIMEOUT) -> ClaimInfo | None:
        """Ask the network now who holds ``module`` (not only what this watcher has seen).

        A liveliness query reaches every live token, so a claim made a moment ago elsewhere
        is not missed because its token is still on its way to our subscriber.
        """
        found = []
        for key in ask_tokens(self.session, f"{PREFIX}/{self.domain}/{module}/**", timeout):
            info = parse_claim(key)
            if info is not None and info.module == module:
                found.append(info)
        with self._lock:
            # What our own subscriber already saw counts too (our own tokens at least).
            found += [c for c in self._tokens.values() if c.module == module]
        return holder_of(found)

    def survey(self, timeout: float = QUERY_TIMEOUT) -> list[ClaimInfo]:
        """Ask the network now for every live claim of the domain, oldest first (what a
        listing shows: it does not wait for this watcher's history)."""
        young = self._made + SETTLE - time.monotonic()
        if young > 0:
            # A session linked a moment ago may not have heard every peer yet (see SETTLE):
            # a listing missing one would say a held module is free.
            time.sleep(young)
        found = self._survey_once(timeout)
        with self._lock:
            found.update(self._tokens)
        return sorted(found.values(), key=ClaimInfo.order)

    def _survey_once(self, timeout: float) -> dict[str, ClaimInfo]:
        found: dict[str, ClaimInfo] = {}
        for key in ask_tokens(self.session, f"{PREFIX}/{self.domain}/**", timeout):
            info = parse_claim(key)
            if info is not None:
                found[info.key] = info
        return found

    def claim(self, module: str, holder: str, node: Any, take: bool = False) -> Claim:
        """Claim ``module`` for ``holder``'s ``node``.

        Args:
            module: The module's slot (``limb1``).
            holder: The operator, ``user@host`` (see :func:`default_holder`).
            node: The node that will send the commands: a :class:`~components.comm.Node`
                (best: its session is then known), or its fully qualified name when it is
                on this object's session.
            take: Take the module over if someone holds it; they learn it at once (their
                :attr:`Claim.lost` is set).

        Returns:
            The claim; release it (or close this object) when done.

        Raises:
            UnknownModuleError: If ``modules`` were given and this is not one of them.
            ClaimRefused: If another operator holds the module and ``take`` is false.
            ClaimError: If the module or holder cannot be written into a claim.
        """
        if self._closed:
            raise ClaimError("this Claims object is closed")
        if self.modules is not None and module not in self.modules:
            raise UnknownModuleError(
                f"there is no module {module!r} to claim; the assembly's modules are "
                f"{', '.join(self.modules) or '(none)'}"
            )
        if not _MODULE.match(module):
            raise ClaimError(f"{module!r} is not a module name (letters, digits and '_')")
        if not holder or any(ch in holder for ch in "/*$?#"):
            raise ClaimError(f"{holder!r} cannot name an operator; write it as user@host")
        if isinstance(node, str):
            fqn, zid = node, str(self.session.zid())
        else:
            fqn, zid = node.fqn, node.zid
        with self._lock:
            for existing in self._mine.values():
                if (existing.module, existing.info.node, existing.info.zid) == (module, fqn, zid):
                    return existing  # claimed already by this node: the same claim
        self._wait_linked(module)
        current = self.current(module)
        while current is None and time.monotonic() < self._made + SETTLE:
            time.sleep(0.1)
            current = self.current(module)
        if current is not None and not take:
            raise ClaimRefused(current)
        since_ns = time.time_ns()
        if current is not None:
            # After the claim taken over even if our clock is behind theirs: a take-over
            # (or a re-claim by the holder itself) must always be the newest token.
            since_ns = max(since_ns, current.since_ns + 1)
        key = claim_key(self.domain, module, since_ns, holder, zid, fqn)
        info = parse_claim(key)
        assert info is not None  # we just wrote it
        token = self.session.liveliness().declare_token(key)
        claim = Claim(self, info, token)
        with self._lock:
            self._mine[key] = claim
            # Known at once here (our subscriber sees our token a moment later): holders()
            # right after claim() already says we hold it.
            self._tokens[key] = info
            changed = self._recompute(module)
        self._announce(changed)
        return claim

    def _wait_linked(self, module: str) -> None:
        """Wait until this session reaches a router or peer (see :data:`LINK_TIMEOUT`).

        Raises:
            ClaimError: If it reaches none in time.
        """
        deadline = time.monotonic() + LINK_TIMEOUT
        while True:
            info = self.session.info
            if list(info.routers_zid()) or list(info.peers_zid()):
                return
            if time.monotonic() > deadline:
                raise ClaimError(
                    f"cannot claim {module}: this session reaches no Zenoh router or peer "
                    f"within {LINK_TIMEOUT:g} s, so who holds it is unknown; check "
                    "MSCTL_ZENOH_CONNECT and that the assembly's router runs"
                )
            time.sleep(0.02)

    def _forget(self, claim: Claim) -> None:
        with self._lock:
            self._mine.pop(claim.info.key, None)
            self._tokens.pop(claim.info.key, None)
            changed = [] if self._closed else self._recompute(claim.module)
        self._announce(changed)

    def close(self) -> None:
        """Release this object's claims and stop watching (idempotent)."""
        with self._lock:
            if self._closed:
                return
            mine = list(self._mine.values())
        for claim in mine:
            claim.release()
        with self._lock:
            self._closed = True
            self._callbacks.clear()
        try:
            self._subscriber.undeclare()
        except Exception as exc:  # the session may be closed already
            _log.debug("claims watcher: subscriber not undeclared: %s", exc)

    def __enter__(self) -> Claims:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _call(callback: Callable[..., Any], *args: Any) -> None:
    try:
        callback(*args)
    except Exception:
        import logging

        logging.getLogger("msctl.claims").exception("claims callback %r failed", callback)

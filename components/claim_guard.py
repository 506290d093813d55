"""Claims enforced on a module's command inputs: the rule a command subscription carries
(:class:`ClaimRule`) and the executor's guard that keeps its senders on the module's claim
holder (:class:`ClaimGuard`), from the holders a :class:`~components.claims.Claims` watcher
sees. Other senders are refused, counted under :data:`NOT_HOLDER` (or :data:`UNCLAIMED`)."""

from __future__ import annotations

import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from components.claims import ClaimInfo, Claims


#: Drop reasons of a command refused by a claim (counted per topic in ``drops``).
NOT_HOLDER = "not_holder"
UNCLAIMED = "unclaimed"


@dataclass(frozen=True)
class ClaimRule:
    """A command subscription's rule: samples only from the holder of ``module``'s claim.

    Set on an interface's ``Subscribe`` (its ``claim``) by the component's builder; the
    executor keeps the subscription's senders on the holder (:class:`ClaimGuard`).

    Attributes:
        module: The module whose claim decides.
        relays: Nodes always taken: components that take commands only from holders
            themselves and forward them (the module's kinematics manager; the steering
            operator), so what they forward is the holder's command.
        required: The assembly says ``claims = "required"``: while nobody holds the module,
            no one but the relays may command it. Otherwise an unclaimed module takes
            commands from anyone (scripts that never claim keep working).
        also: More modules the same commands move (a Twist on ``cmd_vel`` steers every
            wheel and limb): the sender must then hold each of them that is claimed, so
            while two operators hold two of them, neither is taken.
    """

    module: str
    relays: tuple[str, ...] = ()
    required: bool = False
    also: tuple[str, ...] = ()

    @property
    def modules(self) -> tuple[str, ...]:
        """Every module the rule watches."""
        return (self.module, *self.also)

    def senders(
        self, holders: Mapping[str, ClaimInfo | None]
    ) -> tuple[frozenset[str] | None, str, str]:
        """Who may command while ``holders`` (module -> its holder, absent or ``None`` when
        free) hold the modules: the senders for :meth:`Subscription.allow
        <components.comm.topics.Subscription.allow>`, what a refusal says, and the drop
        reason it is counted under."""
        held = {m: h for m in self.modules if (h := holders.get(m)) is not None}
        free = [m for m in self.modules if m not in held]
        operators = {(h.node, h.zid) for h in held.values()}
        if len(operators) > 1:
            named = "; ".join(f"{m} by {h.holder} (node {h.node})" for m, h in sorted(held.items()))
            return (
                frozenset(self.relays),
                f"its modules are claimed by different operators ({named}): one operator "
                "must hold them all",
                NOT_HOLDER,
            )
        if self.required and free:
            return (
                frozenset(self.relays),
                f"{', '.join(free)} take{'s' if len(free) == 1 else ''} commands only from "
                'the holder of a claim (the assembly says claims = "required") and nobody '
                "holds it: claim it first (msctl teleop, or a script under msctl run)",
                UNCLAIMED,
            )
        if held:
            module, holder = next(iter(held.items()))
            return (
                frozenset({f"{holder.node}@{holder.zid}", *self.relays}),
                f"{', '.join(held) if len(held) > 1 else module} is claimed by {holder.holder} "
                f"(node {holder.node}) since {holder.since_text()}; only the holder may "
                "command it (msctl claims)",
                NOT_HOLDER,
            )
        return None, "", NOT_HOLDER


class ClaimGuard:
    """Keeps guarded subscriptions' senders on their modules' claim holders.

    Args:
        claims: The watcher whose holders decide (its ``on_change`` drives this guard).
    """

    def __init__(self, claims: Claims) -> None:
        self.claims = claims
        self._lock = threading.Lock()
        self._guarded: dict[str, list[tuple[Any, ClaimRule]]] = {}
        claims.on_change(self._on_change)

    def add(self, subscription: Any, rule: ClaimRule) -> None:
        """Guard ``subscription`` (made ``guarded``) by ``rule``, from now on.

        Until the watcher has heard of a claim, the module is taken as free: for a moment
        after a (re)start, an open assembly's module takes anyone's commands, a required
        one's no one's.
        """
        with self._lock:
            for module in rule.modules:
                self._guarded.setdefault(module, []).append((subscription, rule))
        self._apply(subscription, rule)

    def discard(self, subscription: Any) -> None:
        """Stop guarding ``subscription`` (its component was removed)."""
        with self._lock:
            for entries in self._guarded.values():
                entries[:] = [e for e in entries if e[0] is not subscription]

    def _apply(self, subscription: Any, rule: ClaimRule) -> None:
        holders = self.claims.holders()
        subscription.allow(*rule.senders({m: holders.get(m) for m in rule.modules}))

    def _on_change(self, module: str, holder: ClaimInfo | None) -> None:
        with self._lock:
            entries = list(self._guarded.get(module, ()))
        for subscription, rule in entries:
            self._apply(subscription, rule)

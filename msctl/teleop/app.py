"""The ``msctl teleop`` screen: keys to the operator, and what moves, at a glance.

The screen is thin: every key goes to the :class:`~msctl.teleop.operator.Operator` (which
owns the core, the deadman and the wire, on its own thread), except the few the app binds
itself: ``space`` e-stops every module this operator holds (:mod:`components.estop`: every
joint manager's ``halt`` at once), ``escape``/``ctrl+c`` stop and quit, ``ctrl+r`` recovers
after an e-stop. Losing the terminal's focus (textual's ``AppBlur``) stops the motion; so
does a claim taken over by another operator, for what it moved.

A module that cannot move (halted from another shell, its joint manager gone: see
:mod:`msctl.teleop.watch`) has its keys refused and the screen says why, never MOVING; so
does a window too small to show what the keys would move (the target area).

It shows the mode and speed, the commanded modules, the deadman (moving or stopped, and why),
the selected joint's position as a bar between its limits (the limb's joints in IK mode, the
twist in drive mode), the health board's latest alarm and the key help. It reads the
operator, the joint handlers and the health board at a bounded rate; nothing on a Zenoh
thread touches a widget (e-stop answers come back as messages from a worker thread).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from rich.text import Text
from textual import events
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.css.query import NoMatches
from textual.message import Message
from textual.widgets import Static

from components.data_monitor.model import level_name
from components.messages import ERROR, OK, STALE, WARN
from msctl.teleop.core import TeleopView
from msctl.teleop.keys import (
    COMMON_HELP,
    DRIVE,
    DRIVE_MOVES,
    HELP,
    IK,
    IK_MOVES,
    JOINT,
    JOINT_MOVES,
)
from msctl.teleop.operator import Operator

#: Seconds between two redraws (10 Hz), however fast keys and samples come.
REFRESH_PERIOD = 0.1
#: Redraws between two looks at the health board.
ALARM_EVERY = 5
#: Characters of a joint's bar between its limits.
BAR_WIDTH = 32
#: Lines the target area needs to show what the keys move (the module line and the selected
#: joint's row): below this, motion keys are refused.
TARGET_LINES = 2
#: Terminal rows below which the key help and spacing give way to the target area.
CRAMPED_ROWS = 20
#: Each mode's motion keys.
_MOVES = {JOINT: JOINT_MOVES, IK: IK_MOVES, DRIVE: DRIVE_MOVES}

_LEVEL_STYLES = {OK: "green", WARN: "bold yellow", ERROR: "bold white on red", STALE: "magenta"}


def bar(position: float | None, lower: float, upper: float, width: int = BAR_WIDTH) -> str:
    """A joint's position between its limits, as ``[----●-------]``.

    A joint without limits (continuous) or without a reading gets a plain word instead.
    """
    if not (math.isfinite(lower) and math.isfinite(upper)) or upper <= lower:
        return "(no limits: continuous)".center(width + 2)
    if position is None or not math.isfinite(position):
        return "[" + "?" * width + "]"
    fraction = min(max((position - lower) / (upper - lower), 0.0), 1.0)
    at = round(fraction * (width - 1))
    return "[" + "─" * at + "●" + "─" * (width - 1 - at) + "]"


def speed_text(view: TeleopView) -> str:
    """The mode's speeds with their units."""
    s = view.speeds
    if view.mode == JOINT:
        return f"{s['joint_speed']:.3g} rad/s (m/s prismatic)"
    if view.mode == IK:
        return f"{s['tip_speed']:.3g} m/s, {s['tip_turn']:.3g} rad/s"
    return f"{s['drive_speed']:.3g} m/s, turn {s['drive_turn']:.3g} rad/s"


def key_name(event: events.Key) -> str:
    """The key as the layouts name it: the character typed when printable, else textual's
    name (``up``, ``tab``, ``shift+tab``)."""
    character = event.character
    if character and len(character) == 1 and character.isprintable() and not character.isspace():
        return character
    return event.key


class TeleopApp(App[None]):
    """``msctl teleop``.

    Args:
        operator: The running operator (its core and outputs).
        link: The link to the assembly (:class:`~msctl.teleop.link.Link`): joint readings,
            the latest alarm, halt and recover.
        template: The assembly's name, for the header.
        refresh_period: Seconds between redraws.
        duration: Quit after this many seconds (None: when asked).
    """

    CSS_PATH = "teleop.tcss"
    TITLE = "msctl teleop"
    BINDINGS = [
        Binding("space", "estop", "E-stop", priority=True),
        Binding("escape", "stop_and_quit", "Stop and quit", priority=True),
        Binding("ctrl+c", "stop_and_quit", "Stop and quit", priority=True, show=False),
        Binding("ctrl+q", "stop_and_quit", "Stop and quit", priority=True, show=False),
        Binding("ctrl+r", "recover", "Recover", priority=True),
    ]

    class ClaimLost(Message):
        """Another operator took a module's claim over (from a Zenoh thread)."""

        def __init__(self, module: str, holder: Any) -> None:
            super().__init__()
            self.module = module
            self.holder = holder

    class Acknowledged(Message):
        """Halt or recover answers came back (from a worker thread)."""

        def __init__(self, verb: str, answers: Sequence[Any]) -> None:
            super().__init__()
            self.verb = verb
            self.answers = list(answers)

    def __init__(
        self,
        operator: Operator,
        link: Any,
        template: str = "",
        refresh_period: float = REFRESH_PERIOD,
        duration: float | None = None,
    ) -> None:
        super().__init__()
        self.operator = operator
        self.link = link
        self.template = template
        self.refresh_period = refresh_period
        self._duration = duration
        self.refreshes = 0
        #: The latest alarm shown.
        self.alarm: Any = None
        #: The latest status line (e-stop answers, refusals, failures).
        self.status = ""
        #: The modules e-stopped and not recovered since.
        self.estopped: list[str] = []
        #: Every halt or recover answer received, oldest first.
        self.answers: list[tuple[str, Any]] = []
        self._failures_seen = 0
        #: Modules that cannot move (halted, gone), and why, as last told to the operator.
        self.unable: dict[str, str] = {}
        #: Modules whose claim another operator took over.
        self._taken: set[str] = set()

    # ------------------------------------------------------------------ layout
    def compose(self) -> ComposeResult:
        """Header, e-stop banner, claims, deadman, target, alarm, status, key help."""
        yield Static(id="header")
        yield Static(id="estop")
        yield Static(id="claims")
        yield Static(id="deadman")
        yield Static(id="target")
        yield Static(id="alarm")
        yield Static(id="status")
        yield Static(id="help")

    def on_mount(self) -> None:
        """Listen for claims taken over, draw, then redraw at the bounded rate."""
        for module, claim in getattr(self.link, "held", {}).items():
            # On a Zenoh thread (at once if already lost): handed over as a message.
            claim.on_lost(lambda holder, m=module: self.post_message(self.ClaimLost(m, holder)))
        self.redraw()
        self.set_interval(self.refresh_period, self.redraw)
        if self._duration:
            self.set_timer(self._duration, self.action_stop_and_quit)

    # ------------------------------------------------------------------ keys
    def on_key(self, event: events.Key) -> None:
        """Every key not bound by the app goes to the operator, but a motion key while the
        window cannot show what it would move."""
        event.stop()
        event.prevent_default()
        key = key_name(event)
        if key in _MOVES.get(self.operator.view().mode, {}) and not self.target_shown():
            self.operator.stop("window too small")
            self.status = (
                f"the window is too small to show what {key!r} would move "
                f"({self.size.width}x{self.size.height}): enlarge it; motion keys are refused"
            )
            self.redraw()
            return
        result = self.operator.press(key)
        if result in ("mode", "select", "refused", "speed"):
            self.redraw()

    def target_shown(self) -> bool:
        """Whether the target area shows what the keys move (at least :data:`TARGET_LINES`)."""
        try:
            return self.query_one("#target", Static).content_region.height >= TARGET_LINES
        except NoMatches:
            return False

    def on_resize(self, event: events.Resize) -> None:
        """A short window gives the key help's room to the target area; one too small to
        show the target while moving stops the motion (checked once laid out)."""
        self.screen.set_class(event.size.height < CRAMPED_ROWS, "cramped")
        self.call_after_refresh(self._check_room)

    def _check_room(self) -> None:
        if not self.target_shown() and self.operator.view().moving:
            self.operator.stop("window too small")

    def follow_modules(self) -> None:
        """Refuse the keys of the modules that cannot move now, and say why; take them
        back when they can (a claim taken over stays refused)."""
        why_not = getattr(self.link, "why_not", None)
        if why_not is None:
            return
        for slot in self.link.modules:
            if slot in self._taken:
                continue
            why = why_not(slot)
            if why and self.unable.get(slot) != why:
                self.unable[slot] = why
                self.operator.block(slot, why, why.split(":", 1)[0])
            elif not why and slot in self.unable:
                del self.unable[slot]
                self.operator.unblock(slot)

    def on_teleop_app_claim_lost(self, message: ClaimLost) -> None:
        """Say it at once, stop what moves that module, refuse its keys from now on."""
        self._taken.add(message.module)
        self.unable.pop(message.module, None)
        holder = message.holder
        reason = (
            f"{message.module} was TAKEN OVER by {holder.holder} (node {holder.node}) at "
            f"{holder.since_text()}: no longer commanded from here (restart with --take to "
            "take it back)"
        )
        self.operator.block(message.module, reason)
        self.status = reason
        self.redraw()

    def on_app_blur(self, event: events.AppBlur) -> None:
        """The terminal lost focus: stop (keys typed elsewhere must not be missed here)."""
        self.operator.stop("focus lost")

    def action_stop_and_quit(self) -> None:
        """Stop (the one stop is on the wire before the app exits), then quit."""
        self.operator.close("quit")
        self.exit()

    def action_estop(self) -> None:
        """Stop, and halt every module this operator holds through its joint manager's
        ``halt``."""
        self.operator.stop("e-stop")
        modules = list(self.link.claimed())
        self.estopped = modules
        self.status = f"E-STOP: halting {', '.join(modules)} ..."
        self.redraw()
        self.run_worker(lambda: self._call("halt", modules), thread=True, group="estop")

    def action_recover(self) -> None:
        """Recover the e-stopped (or every commanded) module."""
        modules = self.estopped or list(self.link.claimed())
        self.status = f"recovering {', '.join(modules)} ..."
        self.run_worker(lambda: self._call("recover", modules), thread=True, group="recover")

    def _call(self, verb: str, modules: list[str]) -> None:
        try:
            answers = getattr(self.link, verb)(modules)
        except Exception as exc:  # reported on screen; the worker must not die silently
            answers = [_Failed(m, str(exc)) for m in modules]
        self.post_message(self.Acknowledged(verb, answers))

    def on_teleop_app_acknowledged(self, message: Acknowledged) -> None:
        """Show each module's answer and its time."""
        self.answers.extend((message.verb, a) for a in message.answers)
        failed = [a for a in message.answers if not a.ok]
        parts = [
            f"{a.module} {'ok' if a.ok else 'FAILED'}"
            + (f" {a.seconds * 1e3:.0f} ms" if a.seconds is not None else " (no answer)")
            for a in message.answers
        ]
        self.status = f"{message.verb}: " + ", ".join(parts)
        if failed:
            self.status += " — " + "; ".join(f"{a.module}: {a.message}" for a in failed)
        if message.verb == "recover" and not failed:
            self.estopped = []
        self.redraw()

    # ------------------------------------------------------------------ drawing
    def redraw(self) -> None:
        """Draw every part from the operator's and the link's state now."""
        try:
            self._draw()
        except NoMatches:
            pass  # mounting, or the app is closing: the next redraw (if any) draws it

    def _draw(self) -> None:
        self.refreshes += 1
        self.follow_modules()
        view = self.operator.view()
        self.query_one("#header", Static).update(self._header(view))
        banner = self.query_one("#estop", Static)
        banner.set_class(bool(self.estopped), "shown")
        banner.update(
            f"E-STOPPED: {', '.join(self.estopped)} (ctrl+r recovers)" if self.estopped else ""
        )
        self.query_one("#claims", Static).update(self._claims(view))
        self.query_one("#deadman", Static).update(self._deadman(view))
        self.query_one("#target", Static).update(self._target(view))
        if self.refreshes % ALARM_EVERY == 1:
            self.alarm = self.link.latest_alarm()
        self.query_one("#alarm", Static).update(self._alarm())
        if self.operator.failures != self._failures_seen:
            self._failures_seen = self.operator.failures
            self.status = self.operator.last_error
        status = self.status or view.note
        self.query_one("#status", Static).update(Text(status, style="italic"))
        self.query_one("#help", Static).update(Text(f"{HELP[view.mode]}\n{COMMON_HELP}"))

    def _header(self, view: TeleopView) -> Text:
        text = Text()
        text.append(" msctl teleop ", style="bold")
        text.append(f"{self.template}  ")
        text.append(f"mode {view.mode.upper()}", style="bold cyan")
        text.append(f"  speed {speed_text(view)}")
        text.append("  " + time.strftime("%H:%M:%S"))
        return text

    def _claims(self, view: TeleopView) -> Text:
        text = Text("modules: ")
        for index, module in enumerate(self.link.modules):
            text.append(", " if index else "")
            text.append(module)
            if module in self.unable:
                state = "GONE" if " GONE" in self.unable[module] else "HALTED"
                text.append(f" {state}", style="bold white on red")
        text.append("    claims: ")
        held = getattr(self.link, "held", {})
        if not held:
            return text.append("none (not claiming)", style="dim")
        for module, claim in held.items():
            if module in self._taken or claim.lost.is_set():
                taker = claim.lost_to.holder if claim.lost_to is not None else "another operator"
                text.append(f"{module} TAKEN by {taker}", style="bold white on red")
            else:
                text.append(f"{module}", style="bold green")
            text.append(" ")
        text.append(f"(held by {next(iter(held.values())).info.holder}", style="dim")
        through = getattr(self.link, "through", None)
        text.append(f" through {through})" if through else ")", style="dim")
        return text

    def _deadman(self, view: TeleopView) -> Text:
        if view.held_back and not view.moving:
            return Text(f"NOT MOVING: {view.held_back}", style="bold white on red")
        if view.moving:
            timeout = "repeating" if view.repeating else "first press"
            return Text(f"MOVING  key {view.key!r} ({timeout})", style="bold green")
        why = f" ({view.stopped_because})" if view.stopped_because else ""
        return Text(f"stopped{why}", style="bold")

    def _target(self, view: TeleopView) -> Text:
        if view.mode == JOINT:
            return self._joints(view.module, view.joint, view.modules)
        if view.mode == IK:
            return self._limb(view.limb)
        return self._drive(view)

    def _joints(self, module: str | None, selected: str | None, modules: Sequence[str]) -> Text:
        text = Text()
        for slot in modules:
            text.append(f" {slot} ", style="reverse bold" if slot == module else "")
        text.append("\n")
        if module is not None:
            text.append_text(self._joint_rows(module, selected))
        return text

    def _joint_rows(self, module: str, selected: str | None, above: int = 1) -> Text:
        """One row per joint: its position as a bar between its limits; as many as the
        target area holds below its first ``above`` lines, the selected one always among
        them."""
        text = Text()
        joints = list(self.link.joints().get(module, ()))
        room = self._target_lines() - above
        if 0 < room < len(joints):
            at = joints.index(selected) if selected in joints else 0
            first = min(max(at - room // 2, 0), len(joints) - room)
            joints = joints[first : first + room]
        for joint in joints:
            position, lower, upper = self.link.joint_state(module, joint)
            mark = ">" if joint == selected else " "
            style = "bold" if joint == selected else "dim"
            shown = "-" if position is None else f"{position:+.3f}"
            text.append(
                f"{mark} {joint:<24} {lower:+7.2f} {bar(position, lower, upper)} "
                f"{upper:+7.2f}  {shown}\n",
                style=style,
            )
        return text

    def _target_lines(self) -> int:
        try:
            return self.query_one("#target", Static).content_region.height
        except NoMatches:
            return 0

    def _limb(self, limb: str | None) -> Text:
        text = Text()
        for slot in self.link.limbs:
            text.append(f" {slot} ", style="reverse bold" if slot == limb else "")
        text.append("\n")
        if limb is None:
            return text
        text.append(f"tip of {limb} in its base frame: {self._tip(limb)}\n")
        text.append_text(self._joint_rows(limb, None, above=2))
        return text

    def _tip(self, limb: str) -> str:
        pose = self.link.tips.tip(limb)
        if pose is None:
            return "unknown (no joint_read yet)"
        x, y, z = pose.translation
        return f"x {x:+.3f}  y {y:+.3f}  z {z:+.3f} m"

    def _drive(self, view: TeleopView) -> Text:
        text = Text(f"Twist on {self.link.drive_target}\n")
        if view.moving:
            text.append("commanding (see the key held above)\n", style="green")
        text.append(
            f"linear speed {view.speeds['drive_speed']:.3g} m/s, "
            f"turn {view.speeds['drive_turn']:.3g} rad/s\n"
        )
        return text

    def _alarm(self) -> Text:
        alarm = self.alarm
        if alarm is None:
            return Text("latest alarm: none", style="dim")
        text = Text("latest alarm: ")
        text.append(level_name(alarm.after), style=_LEVEL_STYLES.get(alarm.after, ""))
        text.append(" " + alarm.line())
        return text


class _Failed:
    """A halt or recover that raised before any module answered."""

    def __init__(self, module: str, message: str) -> None:
        self.module = module
        self.ok = False
        self.message = message
        self.seconds: float | None = None


def run_app(
    assembly: Any,
    modules: Sequence[str] = (),
    mode: str = JOINT,
    settings: Any = None,
    cmd_vel: str | None = None,
    stamped: bool = False,
    duration: float | None = None,
    take: bool = False,
) -> None:
    """Run the screen on the data plane until the operator quits (or ``duration`` passes).

    Whatever ends it (quit, an exception, a signal), any motion ends with its one stop on the
    wire before the session closes.

    Raises:
        InputError: If the mode cannot be used with these modules.
        MsctlError: If another operator holds a module's claim (and not ``take``).
    """
    from msctl.errors import InputError
    from msctl.launcher.plan import this_host
    from msctl.plane import connected
    from msctl.teleop.core import TeleopCore
    from msctl.teleop.link import Link

    with connected("teleop") as node:
        link = Link.open(
            node,
            assembly,
            modules,
            cmd_vel=cmd_vel,
            stamped=stamped,
            take=take,
            station=this_host(),
        )
        try:
            why = link.unavailable.get(mode)
            if why:
                raise InputError(f"--mode {mode}: {why}")
            try:
                core = TeleopCore(settings, link.joints(), link.limbs, link.drive_target, mode)
            except ValueError as exc:
                raise InputError(f"--mode {mode}: {exc}") from exc
            operator = Operator(core, link.outputs()).start()
            app = TeleopApp(operator, link, template=assembly.template, duration=duration)
            try:
                with _quit_on_signals(app):
                    app.run()
            finally:
                # textual ends the app on an exception in a handler (printing it itself)
                # with a non-zero return code; anything raised here leaves it None.
                operator.close("quit" if app.return_code == 0 else "crash")
        finally:
            link.close()
    if app.return_code:
        raise SystemExit(app.return_code)


@contextmanager
def _quit_on_signals(app: TeleopApp) -> Iterator[None]:
    """SIGTERM and SIGHUP (the terminal went away) stop and quit like Esc."""
    import signal
    import threading

    def leave(signum: int, _frame: Any) -> None:
        # A handler runs on the app's own thread between two of its steps: ask from
        # another thread, as textual wants.
        def ask() -> None:
            try:
                app.call_from_thread(app.action_stop_and_quit)
            except Exception:
                pass  # the app is gone already: run_app's finally stops

        threading.Thread(target=ask, daemon=True).start()

    previous = {number: signal.signal(number, leave) for number in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)

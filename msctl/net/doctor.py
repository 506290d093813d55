"""``msctl doctor``'s checks: the preflight of a field day, on one computer.

Each check returns :class:`Finding` rows (OK, WARN or ERROR with what to do). Time and the
session come from the caller, so tests give a skewed clock and a real loopback router.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import shutil
import threading
from collections.abc import Callable, Iterable
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from components.motors.emulation import EMULATE_ENV
from components.supervision.protocol import DoctorFinding

OK, WARN, ERROR = "OK", "WARN", "ERROR"
#: Clock offsets beyond these break watchdogs and bag timestamps.
CLOCK_WARN_S = 0.050
CLOCK_ERROR_S = 0.500
#: The clock is compared over the samples of this many seconds after the first, at most
#: :data:`CLOCK_SAMPLES` of them (see :func:`measure_clock_offset`).
CLOCK_WINDOW_S = 0.5
CLOCK_SAMPLES = 20
#: Certificates expiring within this are flagged.
EXPIRY_WARN = timedelta(days=7)
#: Free space for logs and bags.
DISK_WARN_BYTES = 2 * 1024**3
DISK_ERROR_BYTES = 200 * 1024**2
#: What a component process imports (checked without importing: fast, no side effects).
RUNTIME_MODULES = ("zenoh", "msgspec", "rosbags", "numpy", "rich", "typer")
SIMULATION_MODULES = ("mujoco",)


#: One line of the preflight: the same struct an agent's doctor answer carries on the wire
#: (host, check, status, detail, value), so a finding is written once.
Finding = DoctorFinding


def version(host: str, lock_file: Path | None) -> list[Finding]:
    """msctl's version and the lock's hash (compared across hosts by the caller)."""
    from msctl import __version__

    found = [Finding(host, "msctl version", OK, __version__, __version__)]
    if lock_file is None or not lock_file.is_file():
        found.append(
            Finding(host, "assembly lock", WARN, "no resolved assembly: run `msctl assemble`")
        )
    else:
        digest = hashlib.sha256(lock_file.read_bytes()).hexdigest()[:16]
        found.append(Finding(host, "assembly lock", OK, f"{lock_file} sha256 {digest}", digest))
    return found


def agreement(findings: Iterable[Finding], check: str) -> list[Finding]:
    """An ERROR per host whose ``check`` value differs from the first host's."""
    rows = [f for f in findings if f.check == check and f.value is not None]
    if not rows:
        return []
    reference = rows[0]
    return [
        Finding(
            f.host,
            f"{check} equal",
            ERROR,
            f"{f.value} here, {reference.value} on {reference.host}: run `msctl update` and "
            "`msctl assemble` so every host runs the same",
            f.value,
        )
        for f in rows[1:]
        if f.value != reference.value
    ]


def clock_offset(host: str, offset_s: float | None, source: str) -> Finding:
    """Grade a clock offset between this computer and ``source``."""
    if offset_s is None:
        return Finding(host, "clock", WARN, f"no timestamped sample from {source} to compare")
    size = abs(offset_s)
    status = ERROR if size > CLOCK_ERROR_S else WARN if size > CLOCK_WARN_S else OK
    detail = f"{offset_s * 1000:+.1f} ms against {source}"
    if status != OK:
        detail += ": synchronise the clocks (chrony/NTP) before driving or recording"
    return Finding(host, "clock", status, detail, offset_s)


def measure_clock_offset(
    session: Any,
    key: str,
    now_ns: Callable[[], int],
    timeout: float = 3.0,
    window: float = CLOCK_WINDOW_S,
) -> tuple[float | None, str]:
    """Offset of this clock from the Zenoh timestamps of the samples on ``key``.

    A sample's timestamp is its publisher's clock as it put it (msctl's sessions stamp what
    they put; a router stamps what comes unstamped); what this clock reads as it arrives is
    later by the transit and by however long this process took to run the callback (a
    loaded computer, the GIL held elsewhere: hundreds of ms on a busy machine, with both
    clocks the same). Both only add to the difference, so the smallest
    difference among the samples of ``window`` seconds after the first (at most
    :data:`CLOCK_SAMPLES`) is the closest to the offset; on a working link the transit
    left in it is far below the 50 ms warning.

    Returns:
        Seconds this clock is ahead (positive) or behind, and the key of the sample it was
        measured on (or ``None`` and ``key`` when nothing timestamped came within
        ``timeout``).
    """
    arrived = threading.Event()
    enough = threading.Event()
    lock = threading.Lock()
    found: dict[str, Any] = {"count": 0}

    def on_sample(sample: Any) -> None:
        if sample.timestamp is None:
            return
        local = now_ns()
        difference = local - sample.timestamp.get_time().timestamp() * 1e9
        with lock:
            found["count"] += 1
            if "difference" not in found or difference < found["difference"]:
                found["difference"] = difference
                found["key"] = str(sample.key_expr)
            if found["count"] >= CLOCK_SAMPLES:
                enough.set()
        arrived.set()

    subscriber = session.declare_subscriber(key, on_sample)
    try:
        if arrived.wait(timeout):
            enough.wait(window)
    finally:
        subscriber.undeclare()
    with lock:
        if "difference" not in found:
            return None, key
        return found["difference"] / 1e9, found["key"]


def router(
    host: str, session: Any, endpoints: Iterable[str], secure: bool | None = None
) -> Finding:
    """Whether this session reaches a router, and over which link type.

    A session on loopback reaches this computer's own router (the field's layout: a
    computer's agent and components are its router's clients over loopback TCP), so what
    leaves the computer is that router's links: mutual TLS when it runs secure.

    Args:
        host: This computer.
        session: The session checked.
        endpoints: The endpoints it connects to.
        secure: Whether this computer's router runs secure (default: ``MSCTL_SECURE=1``
            here, as ``msctl agent --secure`` and ``msctl up --secure`` set it when they
            start their router).
    """
    endpoints = list(endpoints)
    protocols = sorted({e.split("/", 1)[0] for e in endpoints})
    routers = list(session.info.routers_zid())
    if not routers:
        return Finding(
            host,
            "router",
            ERROR,
            f"no router at {', '.join(endpoints)}: run `msctl up` or `msctl router`",
            None,
        )
    link = "/".join(protocols)
    if secure is None:
        secure = os.environ.get("MSCTL_SECURE") == "1"
    if "tls" not in protocols and secure and endpoints and not any(map(_leaves, endpoints)):
        detail = f"{routers[0]} over {link} on loopback: this computer's secure router, "
        return Finding(host, "router", OK, detail + "mutual TLS beyond it", "tls")
    status = OK if "tls" in protocols else WARN
    detail = f"{routers[0]} over {link}"
    if status == WARN:
        detail += ": not encrypted; run `msctl net init` and `msctl up --secure` in the field"
    return Finding(host, "router", status, detail, link)


def senders(host: str, session: Any, assembly: Any, domain: int = 0) -> Finding:
    """Nothing but their declared senders publishes the modules' raw motor commands and
    feedback, by the roles the interfaces declare (:func:`components.roles.intruders`): a
    bag played onto the live assembly, a stray script or a second motor interface is named
    here (each module also refuses and counts its samples)."""
    from components.comm.graph import snapshot
    from components.comm.liveliness import EntityKind
    from components.roles import intruders

    publishers: dict[str, list[str]] = {}
    for entity in snapshot(session, domain).entities():
        if entity.kind is EntityKind.PUBLISHER and entity.topic is not None:
            publishers.setdefault(entity.topic, []).append(entity.node_fqn)
    found = intruders(assembly, publishers)
    if not found:
        return Finding(
            host, "senders", OK, "only their own components publish the modules' motor topics"
        )
    named = "; ".join(
        f"{i.node} publishes {i.topic} ({i.role.value}: only {', '.join(i.allowed)} may)"
        for i in found
    )
    return Finding(
        host, "senders", WARN, f"{named}: stop it (the module refuses it, counting)", len(found)
    )


def _leaves(endpoint: str) -> bool:
    """Whether ``endpoint`` reaches beyond this computer (one it cannot read: yes)."""
    from msctl.net.endpoints import EndpointError, parse

    try:
        return parse(endpoint).leaves_computer
    except EndpointError:
        return True


def certificates(host: str, home: Path | None, now: datetime | None = None) -> list[Finding]:
    """Every identity of the fleet: verifies against the CA, not expiring within 7 days; one
    whose certificate cannot be read is an ERROR naming its file, and the others are still
    checked."""
    from msctl.net import pki

    if not pki.trusts(home):
        return [Finding(host, "certificates", WARN, "no fleet CA: run `msctl net init`")]
    now = now or datetime.now(UTC)
    found = []
    identities, broken = pki.scan(home)
    for cert, why in broken:
        found.append(Finding(host, f"cert {cert.parent.name}", ERROR, why))
    for identity in identities:
        problem = pki.verify(identity.cert, home)
        left = identity.expires - now if identity.expires else None
        if problem:
            row = Finding(
                host,
                f"cert {identity.common_name}",
                ERROR,
                f"{identity.cert} does not verify: {problem}",
            )
        elif left is None or left <= timedelta(0):
            row = Finding(
                host,
                f"cert {identity.common_name}",
                ERROR,
                f"expired: {pki.reissue_hint(identity.common_name)}",
            )
        elif left < EXPIRY_WARN:
            row = Finding(
                host,
                f"cert {identity.common_name}",
                WARN,
                f"expires in {left.days} days: {pki.reissue_hint(identity.common_name)}",
            )
        else:
            row = Finding(
                host, f"cert {identity.common_name}", OK, f"valid until {identity.expires:%Y-%m-%d}"
            )
        found.append(row)
    return found


def key_modes(host: str, home: Path | None) -> list[Finding]:
    """The private keys under ``MSCTL_HOME/net`` (the CA's, every identity's) are 0600:
    ``MSCTL_HOME/net`` is copied between computers, and a copy can lose the modes."""
    from msctl.net import pki

    loose = pki.loose_keys(home)
    if not loose:
        where = pki.net_dir(home)
        if not where.is_dir():
            return [Finding(host, "key modes", OK, f"no private keys here ({where})")]
        return [Finding(host, "key modes", OK, f"every private key in {where} is 0600")]
    return [Finding(host, "key modes", ERROR, why, str(key)) for key, why in loose]


def devices(host: str, assembly: Any, simulated: bool, sys_root: Path = Path("/")) -> list[Finding]:
    """The CAN interfaces and serial ports this host's modules' buses need."""
    found = []
    for module in assembly.modules:
        if module.host != host:
            continue
        channel = module.bus.channel
        check = f"bus {module.slot}"
        if simulated:
            found.append(Finding(host, check, OK, f"{channel} not needed: simulated"))
            continue
        if os.environ.get(EMULATE_ENV) == "1":
            # A rehearsal's robot computer: the motor interface emulates the bus itself.
            found.append(
                Finding(host, check, OK, f"{channel} not needed: emulated ({EMULATE_ENV})")
            )
            continue
        if channel.startswith("/"):
            path = sys_root / channel.lstrip("/")
            if not path.exists():
                found.append(
                    Finding(
                        host,
                        check,
                        ERROR,
                        f"serial port {channel} is missing: plug "
                        "the adapter in, or fix the unit's calibration file",
                    )
                )
            elif not os.access(path, os.R_OK | os.W_OK):
                found.append(
                    Finding(
                        host,
                        check,
                        ERROR,
                        f"serial port {channel} is not "
                        "readable and writable: add the user to group dialout",
                    )
                )
            else:
                found.append(Finding(host, check, OK, f"serial port {channel}"))
        else:
            path = sys_root / "sys" / "class" / "net" / channel
            if not path.exists():
                found.append(
                    Finding(
                        host,
                        check,
                        ERROR,
                        f"CAN interface {channel} is missing: "
                        f"`ip link set {channel} up type can bitrate "
                        f"{module.bus.bitrate or 1000000}`",
                    )
                )
            else:
                found.append(Finding(host, check, OK, f"CAN interface {channel}"))
    return found


def disk(host: str, directory: Path) -> Finding:
    """Free space where logs and bags go."""
    while not directory.exists() and directory != directory.parent:
        directory = directory.parent
    free = shutil.disk_usage(directory).free
    status = ERROR if free < DISK_ERROR_BYTES else WARN if free < DISK_WARN_BYTES else OK
    detail = f"{free / 1024**3:.1f} GiB free at {directory}"
    if status != OK:
        detail += ": free space (old bags: `msctl bag info`) before recording"
    return Finding(host, "disk", status, detail, free)


def python_env(host: str, simulated: bool) -> list[Finding]:
    """The modules components import are installed."""
    wanted = RUNTIME_MODULES + (SIMULATION_MODULES if simulated else ())
    missing = [m for m in wanted if importlib.util.find_spec(m) is None]
    if missing:
        return [
            Finding(
                host,
                "python",
                ERROR,
                f"missing {', '.join(missing)}: `pip install -e .` in the venv msctl runs from",
            )
        ]
    return [Finding(host, "python", OK, f"imports {', '.join(wanted)}")]


def worst(findings: Iterable[Finding]) -> str:
    """The worst status among ``findings``."""
    statuses = {f.status for f in findings}
    return ERROR if ERROR in statuses else WARN if WARN in statuses else OK


def clean(exc: BaseException) -> str:
    """An exception as one line for the operator: no Rust source path, no traceback."""
    from components.comm.session import zenoh_reason

    return " ".join(zenoh_reason(exc).split())


def this_computer(
    host: str,
    session: Any,
    endpoints: Iterable[str],
    domain: int = 0,
    clock_timeout: float = 1.0,
    now_ns: Callable[[], int] | None = None,
    router_error: str | None = None,
) -> list[Finding]:
    """Every check of this computer, through an open ``session`` (a supervisor's or agent's,
    for ``msctl doctor --all``; the command's own otherwise).

    Each check runs whatever the others found: with no router (``session`` ``None``) the
    certificates, keys, buses, disk and Python are still checked, and a check that fails
    in itself is an ERROR naming it, never the end of the preflight.

    Args:
        router_error: Why no session could be opened (with ``session`` ``None``).
    """
    import time

    from components.assembly import lock_path, state_dir

    found: list[Finding] = []

    def run(check: str, step: Callable[[], Finding | list[Finding]]) -> None:
        try:
            result = step()
        except Exception as exc:  # a preflight reports every check, whatever one raised
            found.append(Finding(host, check, ERROR, f"could not be checked: {clean(exc)}"))
            return
        found.extend(result if isinstance(result, list) else [result])

    assembly = _assembly(found, host)
    run("msctl version", lambda: version(host, lock_path() if assembly else None))
    if session is None:
        detail = router_error or f"no router at {', '.join(endpoints)}"
        found.append(Finding(host, "router", ERROR, detail))
        found.append(Finding(host, "clock", WARN, "not compared: no router to take samples from"))
    else:
        run("router", lambda: router(host, session, list(endpoints)))

        def clock() -> Finding:
            offset, source = measure_clock_offset(
                session, f"{domain}/**", now_ns or time.time_ns, clock_timeout
            )
            return clock_offset(host, offset, source)

        run("clock", clock)
        if assembly is not None:
            run("senders", lambda: senders(host, session, assembly, domain))
    run("certificates", lambda: certificates(host, None))
    run("key modes", lambda: key_modes(host, None))
    simulated = assembly is None or host not in {m.host for m in assembly.modules}
    if assembly is not None:
        run("buses", lambda: devices(host, assembly, simulated))
    run("disk", lambda: disk(host, state_dir()))
    run("python", lambda: python_env(host, simulated))
    return found


def _assembly(found: list[Finding], host: str) -> Any:
    """The resolved assembly, or ``None`` (no lock: ``version`` says so; a broken one is an
    ERROR here)."""
    from components.assembly import AssemblyError, load_assembly, lock_path

    try:
        return load_assembly()
    except AssemblyError as exc:
        if lock_path().is_file():
            found.append(Finding(host, "assembly", ERROR, clean(exc)))
        return None
    except Exception as exc:  # a preflight reports every check, whatever one raised
        found.append(Finding(host, "assembly", ERROR, f"could not be read: {clean(exc)}"))
        return None

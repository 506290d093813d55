"""Shared fixtures: real Zenoh routers and sessions on 127.0.0.1, random ports, no multicast.

Also the session-wide setup of ``pyzeros``' codec compiler (see :func:`pytest_configure`).
"""

from __future__ import annotations

import getpass
import os
import signal
import socket
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from components.comm.session import SessionSettings, open_session

# --------------------------------------------------------------------------- pyzeros' codecs
#: Where ``cydr`` (the codec compiler under ``pyzeros``) keeps what it compiles. By default it
#: is ``./.cydr_cache`` (in the repository), filled the first time a message is serialized,
#: inside whichever test did it and under that test's timeout: on a loaded machine the
#: compile alone outlasted it. A per-user directory under the system's temporary directory
#: instead, shared by sessions (cydr locks its builds), so it is compiled once per machine.
CODEC_CACHE_ENV = "CYDR_CACHE_DIR"


def codec_cache_dir() -> Path:
    """The directory cydr compiles into: ``$CYDR_CACHE_DIR`` when set, else a per-user one
    under the system's temporary directory."""
    given = os.environ.get(CODEC_CACHE_ENV)
    if given:
        return Path(given)
    user = os.getuid() if hasattr(os, "getuid") else getpass.getuser()
    return Path(tempfile.gettempdir()) / f"msctl-test-cydr-{user}"


#: Where the tests' subprocesses keep their bytecode. Machines that set
#: PYTHONDONTWRITEBYTECODE (this one, and CI's image) made every ``msctl`` command and every
#: component process of a run compile the checkout again: about 0.15 s of CPU each, hundreds
#: of times a run. Per user under the system's temporary directory, so a clean clone's first
#: run fills it and later ones reuse it (Python checks each source's size and time).
BYTECODE_ENV = "PYTHONPYCACHEPREFIX"

#: Where Hypothesis keeps its example database and caches. By default it is ``./.hypothesis``
#: in whatever directory the tests run from (the checkout). Per user under the system's
#: temporary directory instead, so failing examples are still replayed run after run.
HYPOTHESIS_ENV = "HYPOTHESIS_STORAGE_DIRECTORY"


def pytest_configure(config: pytest.Config) -> None:
    """Point cydr at :func:`codec_cache_dir` before any test module imports it, Hypothesis
    at a temporary directory (:data:`HYPOTHESIS_ENV`), and let the tests' subprocesses keep
    their bytecode (see :data:`BYTECODE_ENV`): a test run writes nothing where it runs.

    cydr reads ``CYDR_CACHE_DIR`` once, when it is imported (at collection, by the test
    modules that import ``pyzeros``), and creates ``./.cydr_cache`` otherwise. Hypothesis
    reads its variable the first time it needs its directory (a test's first example).
    """
    # A run started in the background of a script (``cmd &`` with no job control) inherits
    # SIGINT ignored, and so would every process the tests start: the Ctrl-C tests' SIGINT
    # would be ignored by the very programs they check. The interpreter's default, back.
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    user = os.getuid() if hasattr(os, "getuid") else getpass.getuser()
    if not os.environ.get(HYPOTHESIS_ENV):
        os.environ[HYPOTHESIS_ENV] = str(
            Path(tempfile.gettempdir()) / f"msctl-test-hypothesis-{user}"
        )
    if os.environ.get("PYTHONDONTWRITEBYTECODE") and not os.environ.get(BYTECODE_ENV):
        os.environ[BYTECODE_ENV] = str(Path(tempfile.gettempdir()) / f"msctl-test-pyc-{user}")
        del os.environ["PYTHONDONTWRITEBYTECODE"]
    cache = codec_cache_dir()
    cache.mkdir(parents=True, exist_ok=True)
    os.environ[CODEC_CACHE_ENV] = str(cache)  # subprocesses inherit it too
    runtime = sys.modules.get("cydr._runtime")
    if runtime is not None:  # imported before us (a plugin): redirect it all the same
        runtime.CYDR_CACHE_DIR = cache


#: Test modules that stand on one shared rehearsal of ``dragon`` (the ``dragon`` fixture), in
#: the order they run: one worker takes them as one unit (:func:`pytest_xdist_make_scheduler`),
#: so the rehearsal is stood up once, not once per module (each costs one to two minutes of
#: both cores). The last one ends it (``down --all``, then ``rehearse down``).
DRAGON_REHEARSAL = (
    "tests/test_rehearse_e2e.py",
    "tests/test_rehearse_presence_e2e.py",
    "tests/test_rehearse_rejoin_e2e.py",
)


def scope_of(nodeid: str) -> str:
    """The unit of work xdist hands one worker for a test: its module, or the shared
    rehearsal's modules together."""
    module = nodeid.split("::", 1)[0]
    return DRAGON_REHEARSAL[0] if module in DRAGON_REHEARSAL else module


def is_rehearsal(scope: str) -> bool:
    """Whether a unit of work stands up a rehearsal (namespaces, five computers' agents and
    routers, a simulator each): one of them takes both cores of a CI machine for minutes."""
    return scope.startswith("tests/test_rehearse_") and scope.endswith("_e2e.py")


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``loadscope`` with :func:`scope_of` for its units, one rehearsal at a time.

    Two or three rehearsals at once on two cores (load 60) starved each other's agents and
    failed CI in its tail (commands over 120 s, a health probe over 60 s); one at a time,
    each gets the machine it was written for while the other workers run the light units.
    A worker left with only rehearsals to take while one runs elsewhere waits for it.
    """
    if config.getvalue("dist") != "loadscope":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class OneRehearsalAtATime(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return scope_of(nodeid)

        def _rehearsing_elsewhere(self, node: Any) -> bool:
            return any(
                is_rehearsal(scope) and not all(unit.values())
                for other, work in self.assigned_work.items()
                if other is not node
                for scope, unit in work.items()
            )

        def _assign_work_unit(self, node: Any) -> None:
            busy = self._rehearsing_elsewhere(node)
            eligible = [scope for scope in self.workqueue if not (busy and is_rehearsal(scope))]
            if not eligible:
                return  # only rehearsals left, one running elsewhere: wait for it to end
            self.workqueue.move_to_end(eligible[0], last=False)
            super()._assign_work_unit(node)

        def mark_test_complete(self, node: Any, item_index: int, duration: float = 0) -> None:
            super().mark_test_complete(node, item_index, duration)
            # A worker left waiting (above) is given work when a rehearsal may have ended.
            for other, work in list(self.assigned_work.items()):
                if other is not node and not self._pending_of(work):
                    self._reschedule(other)

    return OneRehearsalAtATime(config, log)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Run the longest units of work first, each unit's tests in order.

    xdist's ``loadscope`` hands whole units (:func:`scope_of`) to the workers in collection
    order (``--no-loadscope-reorder`` in addopts: by default xdist reorders by the count of
    tests, which put the few-test rehearsals last, together): a long unit collected last ran
    alone at the end while the other workers sat idle (the suite's tail). Longest-first is
    the classic fix. A unit's length is estimated: a rehearsal (namespaces, five computers'
    agents) outweighs any count of ``e2e`` tests, which stands in for the length of the
    rest. The scheduler runs the rehearsals one at a time, on whichever worker is free.
    """
    del config
    weight: dict[str, int] = {}
    for item in items:
        scope = scope_of(item.nodeid)
        weight.setdefault(scope, 1000 if is_rehearsal(scope) else 0)
        weight[scope] += item.get_closest_marker("e2e") is not None
    order = {module: i for i, module in enumerate(DRAGON_REHEARSAL)}
    items.sort(
        key=lambda item: (
            -weight[scope_of(item.nodeid)],
            scope_of(item.nodeid),
            order.get(item.nodeid.split("::", 1)[0], 0),
        )
    )


def pytest_collection_finish(session: pytest.Session) -> None:
    """Compile the codecs the selected tests use, once, before the first test runs.

    This hook runs outside every test's timeout. Only sessions that selected a test from a
    module using ``pyzeros`` pay for it (a few seconds when cached, tens of seconds to
    compile on a busy machine).
    """
    if not any(_uses_pyzeros(item) for item in session.items):
        return
    from pyzeros.builtin_msgs import Attachment

    # The one cydr type the tests serialize: pyzeros' rmw_zenoh attachment (their messages
    # are ros2_pyterfaces' cyclone types, which need no compiling).
    encoded = Attachment(sequence_number=1, source_timestamp=2).serialize()
    assert Attachment.deserialize(encoded).sequence_number == 1


def _uses_pyzeros(item: pytest.Item) -> bool:
    module = getattr(item, "module", None)
    if module is None:
        return False
    for value in vars(module).values():
        origin = getattr(value, "__module__", None) or getattr(value, "__name__", "")
        if isinstance(origin, str) and origin.split(".")[0] == "pyzeros":
            return True
    return False


def free_port() -> int:
    """A TCP port that was free a moment ago on 127.0.0.1."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_until(
    predicate: Callable[[], Any],
    timeout: float = 30.0,
    what: str | Callable[[], str] = "",
    interval: float = 0.02,
) -> Any:
    """Poll ``predicate`` until it returns something truthy; fail the test on timeout.

    Args:
        predicate: What to poll.
        timeout: Seconds before failing: generous by default, as a loaded CI machine needs
            (a wait ends as soon as its condition holds; 5 s failed a loaded full run).
        what: Said in the failure (what was awaited); a callable is asked only then, so it
            can tell the state the wait ended in.
        interval: Seconds between polls.
    """
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            said = what() if callable(what) else what
            raise AssertionError(f"not within {timeout} s: {said or 'condition'}")
        time.sleep(interval)


_resolved: dict[tuple[str, tuple[tuple[str, str], ...]], Any] = {}


def resolved_assembly(directory: Any, template: str, units: dict[str, str] | None = None) -> Any:
    """A shipped template resolved (with ``units`` for some slots) and written under
    ``directory``; loaded as the launcher would load it. Cached per template and units."""
    from components.assembly import load_assembly
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    key = (template, tuple(sorted((units or {}).items())))
    if key not in _resolved:
        resolution = resolve(template, units or {})
        target = write_resolution(directory / f"{template}-assembly", resolution)
        _resolved[key] = load_assembly(target)
    return _resolved[key]


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """A real Zenoh router listening on a random loopback port; yields its endpoint."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    settings = SessionSettings(mode="router", connect=(), listen=(endpoint,))
    router = open_session(settings)
    try:
        yield endpoint
    finally:
        router.close()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    """Peer settings that reach the test router and nothing else."""
    return SessionSettings(
        mode="peer", connect=(router_endpoint,), listen=("tcp/127.0.0.1:0",), multicast=False
    )


@pytest.fixture
def zenoh_env(router_endpoint: str, monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    """Environment for msctl subprocesses so they join the test router only."""
    env = {
        "MSCTL_ZENOH_CONNECT": router_endpoint,
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
    }
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    return env


@pytest.fixture
def open_sessions(session_settings: SessionSettings) -> Iterator[Callable[[], Any]]:
    """A factory of peer sessions on the test router; every one is closed at teardown."""
    sessions: list[Any] = []

    def make() -> Any:
        session = open_session(session_settings)
        sessions.append(session)
        return session

    try:
        yield make
    finally:
        for session in reversed(sessions):
            session.close()


# --------------------------------------------------------------------------- quick opening
#: Zenoh waits ``scouting/delay`` (0.5 s) in ``zenoh.open`` for the first connections; tests
#: that poll for routes anyway can skip it. Modules opt in by overriding ``router_endpoint``
#: and ``session_settings`` with :func:`quick_router` and :func:`quick_peer_settings`.
QUICK_OPEN = {"scouting/delay": 0}


def quick_router() -> Iterator[str]:
    """A real loopback router that opens at once (use as ``yield from quick_router()``)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(
        SessionSettings(mode="router", connect=(), listen=(endpoint,), extra=dict(QUICK_OPEN))
    )
    try:
        yield endpoint
    finally:
        router.close()


def quick_peer_settings(router_endpoint: str) -> SessionSettings:
    """Peer settings joining ``router_endpoint`` that open at once (routes come soon after)."""
    return SessionSettings(
        mode="peer",
        connect=(router_endpoint,),
        listen=("tcp/127.0.0.1:0",),
        multicast=False,
        extra=dict(QUICK_OPEN),
    )


@pytest.fixture(scope="module")
def endpoint() -> Iterator[str]:
    """A real router on a random loopback port, for the whole module."""
    yield from quick_router()


@pytest.fixture(scope="module")
def net_env(endpoint: str) -> dict[str, str]:
    """Network settings every subprocess of the module gets: its router only, no multicast."""
    return {
        "MSCTL_ZENOH_CONNECT": endpoint,
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
    }


@pytest.fixture(scope="session")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """One rehearsal of ``dragon`` on ``wifi`` links shared by :data:`DRAGON_REHEARSAL`'s
    modules (a ``rehearse_rigs.Stage``), taken down at the end of the session, also on
    failure, leaving no namespace."""
    from rehearse_rigs import Stage, rehearsed

    with rehearsed(Stage(tmp_path_factory.mktemp("dragon"))) as stage:
        yield stage

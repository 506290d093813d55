"""Real ROS 2 for the tests: rclpy (the ``ros`` extra) on Fast DDS, kept to this machine.

Every test that starts DDS takes a ROS domain of its own (:func:`ros_domain`): a lock file per
domain id under the system's temporary directory, held while the test runs, so two tests,
two xdist workers or two runs on one machine never meet on one DDS graph. Discovery stays on
this computer (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``).

:class:`RosPeer` is the other side: an ordinary rclpy node with the message packages from the
package index (``std_msgs``, ``sensor_msgs``, ``std_srvs`` ...), spun on its own thread in its
own context (its own DDS participant), the way a ROS 2 user's node would be.
"""

from __future__ import annotations

import contextlib
import fcntl
import importlib.util
import os
import random
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

HAVE_RCLPY = importlib.util.find_spec("rclpy") is not None
#: Marks tests that need real rclpy (skipped, saying why, where the ``ros`` extra is missing).
needs_rclpy = pytest.mark.skipif(
    not HAVE_RCLPY, reason="needs rclpy: pip install '.[ros]' (ROS 2 Jazzy wheels)"
)
#: Domain ids tests take (0 is every ROS install's default; 101 is the last id whose DDS
#: ports stay below Linux's ephemeral range).
DOMAINS = range(1, 102)
#: The rmw the tests use: the only one the ``ros`` extra installs.
RMW = "rmw_fastrtps_cpp"


def ros_environment(domain: int) -> dict[str, str]:
    """Environment variables of a ROS 2 process on ``domain``, discovering on localhost only."""
    return {
        "ROS_DOMAIN_ID": str(domain),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": RMW,
    }


@contextlib.contextmanager
def ros_domain() -> Iterator[int]:
    """A ROS domain id no other test on this machine holds, held until the block ends."""
    folder = Path(tempfile.gettempdir()) / f"msctl-test-ros-domains-{os.getuid()}"
    folder.mkdir(parents=True, exist_ok=True)
    candidates = list(DOMAINS)
    random.shuffle(candidates)
    for domain in candidates:
        handle = open(folder / f"{domain}.lock", "w")  # noqa: SIM115 (held past the loop)
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        try:
            yield domain
        finally:
            handle.close()  # releases the lock
        return
    raise RuntimeError(f"every ROS domain in {DOMAINS} is held by other tests")


@pytest.fixture
def domain(monkeypatch: pytest.MonkeyPatch) -> Iterator[int]:
    """A ROS domain of this test's own; this process's DDS discovery stays on localhost."""
    with ros_domain() as held:
        for key, value in ros_environment(held).items():
            monkeypatch.setenv(key, value)
        yield held


class RosPeer:
    """An rclpy node as a ROS 2 user writes one, in its own context, spun on a thread.

    Args:
        domain: ROS domain id.
        name: Node name.
        namespace: Node namespace.
    """

    def __init__(self, domain: int, name: str = "peer", namespace: str = "/") -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import MultiThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self.context = Context()
        rclpy.init(
            context=self.context,
            domain_id=domain,
            signal_handler_options=SignalHandlerOptions.NO,
        )
        self.node = rclpy.create_node(name, namespace=namespace, context=self.context)
        self.executor = MultiThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        #: What ended the spinning thread early, if anything (a test's failure says it).
        self.spin_error: BaseException | None = None
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception as exc:
                if self._stop.is_set():
                    return
                self.spin_error = exc
                raise

    def spinning(self) -> str:
        """Whether callbacks are still called: ``spinning``, or what stopped it."""
        if self._thread.is_alive():
            return "spinning"
        return f"not spinning: {self.spin_error!r}"

    def collect(self, msg_type: Any, topic: str, qos: Any = 10) -> list[Any]:
        """Subscribe to ``topic``; returns the list the messages are appended to."""
        received: list[Any] = []
        self.node.create_subscription(msg_type, topic, received.append, qos)
        return received

    def call(self, srv_type: Any, service: str, request: Any, timeout: float = 20.0) -> Any:
        """Call a service and wait for its answer (``None`` if none came in ``timeout``)."""
        client = self.node.create_client(srv_type, service)
        try:
            if not client.wait_for_service(timeout_sec=timeout):
                return None
            done = threading.Event()
            future = client.call_async(request)
            future.add_done_callback(lambda _: done.set())
            if not done.wait(timeout):
                return None
            return future.result()
        finally:
            self.node.destroy_client(client)

    def nodes(self) -> set[str]:
        """Fully qualified names of the nodes on the graph."""
        return {
            f"{namespace.rstrip('/')}/{name}"
            for name, namespace in self.node.get_node_names_and_namespaces()
        }

    def serve(self, srv_type: Any, service: str, handler: Callable[[Any, Any], Any]) -> Any:
        """Serve a service with ``handler(request, response) -> response``."""
        return self.node.create_service(srv_type, service, handler)

    def close(self) -> None:
        """Stop spinning and shut the context down."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        self.context.try_shutdown()

    def __enter__(self) -> RosPeer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

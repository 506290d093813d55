"""Build a data monitor from the resolved assembly, and bind its graph and supervisor feeds.

The core is pure; the builder's ``on_bound`` hook (:class:`MonitorFeeds`) follows the graph
and asks the supervisors on the executor's session, posting what it learns into the executor
thread with ``Executor.call_soon``. Both are closed with the component's other resources.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

from components.assembly import ComponentPlan, ResolvedAssembly
from components.build import BuiltComponent, config_from_params, node_name
from components.data_monitor.core import DataMonitorConfig, DataMonitorCore
from components.data_monitor.feeds import NodeFeed, SupervisorPoller
from components.data_monitor.interface import data_monitor_interface
from components.data_monitor.plan import board_for

if TYPE_CHECKING:
    from components.executor.executor import Component, Executor
    from components.supervision.protocol import RunDocument


class MonitorFeeds:
    """The data monitor's ``on_bound`` hook: a graph feed and a supervisor poller.

    Args:
        built: The built data monitor; the feeds are added to its resources.
        nodes: Fully qualified names of the nodes to follow.
    """

    def __init__(self, built: BuiltComponent, nodes: Iterable[str]) -> None:
        self.built = built
        self.nodes = frozenset(nodes)
        self.poller: SupervisorPoller | None = None

    def poke(self) -> None:
        """Ask the supervisors again soon (called by the core when a node leaves)."""
        if self.poller is not None:
            self.poller.poke()

    def __call__(self, executor: Executor, component: Component) -> None:
        """Start the feeds on ``executor``'s session (called once, before it runs)."""

        def on_node(node: str, count: int) -> None:
            executor.call_soon(component, "on_node_instances", node, count)

        def on_supervisors(documents: list[RunDocument], unanswered: list[str]) -> None:
            executor.call_soon(component, "on_supervisors", documents, unanswered)

        # Published as bytes the core encodes itself, where the publisher takes bytes.
        publish_raw = getattr(component.publishers.get("/diagnostics_agg"), "publish_raw", None)
        if publish_raw is not None and isinstance(component.core, DataMonitorCore):
            component.core.publish_encoded(publish_raw)
        feed = NodeFeed(self.nodes, on_node)
        graph = feed.follow(executor.graph)
        self.built.resources.append(feed)
        executor.call_soon(component, "on_graph_ready")
        self.poller = SupervisorPoller(component.node, graph, on_supervisors).start()
        self.built.resources.append(self.poller)


def build(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any]
) -> BuiltComponent:
    """A data monitor watching every module and station of ``assembly``.

    Params: :class:`DataMonitorConfig` fields.

    Raises:
        BuildError: If a parameter is out of range or not a number.
    """
    del options
    config = config_from_params(plan, DataMonitorConfig)
    board = board_for(assembly, stale_after=config.stale_after, max_items=config.max_items)
    feeds_holder: list[MonitorFeeds] = []
    core = DataMonitorCore(
        plan.name, board, config, on_supervisor_needed=lambda: feeds_holder[0].poke()
    )
    built = BuiltComponent(
        core, data_monitor_interface(board.watched), plan.namespace, node_name(plan.name)
    )
    feeds = MonitorFeeds(built, board.nodes())
    feeds_holder.append(feeds)
    built.on_bound = feeds
    return built

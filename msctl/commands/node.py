"""``msctl node``: the nodes on the network (msctl components and ROS 2 nodes alike)."""

from __future__ import annotations

import typer

app = typer.Typer(help="Nodes on the network.", no_args_is_help=True)


@app.command("list")
def list_nodes(
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
) -> None:
    """List every node (what `ros2 node list` would show)."""
    from components.comm.graph import snapshot
    from msctl.console import out, print_json
    from msctl.plane import connected

    with connected("node_list") as node:
        nodes = [n for n in snapshot(node.session, node.domain).nodes() if n.fqn != node.fqn]
    if json_output:
        print_json([{"name": n.fqn, "namespace": n.namespace, "zid": n.zid} for n in nodes])
        return
    for n in nodes:
        out.print(n.fqn, highlight=False)

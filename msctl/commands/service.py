"""``msctl service``: list and call services, as ``ros2 service`` does."""

from __future__ import annotations

import typer

from msctl.errors import InputError, NetworkError, NotFoundError, OperationTimeout

app = typer.Typer(help="Services: list and call.", no_args_is_help=True)


@app.command("list")
def list_services(
    show_types: bool = typer.Option(False, "--show-types", "-t", help="Show each service's type."),
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
) -> None:
    """List every service on the network."""
    from components.comm.graph import snapshot
    from msctl.console import out, print_json
    from msctl.plane import connected

    with connected("service_list") as node:
        services = {
            k: v for k, v in snapshot(node.session, node.domain).services().items() if v.servers
        }
    if json_output:
        print_json(
            [
                {"name": s.name, "types": sorted(s.types), "servers": s.servers}
                for s in services.values()
            ]
        )
        return
    for s in services.values():
        line = s.name + (f" [{', '.join(sorted(s.types))}]" if show_types else "")
        out.print(line, highlight=False, markup=False)


def _check_type_on_graph(node: object, service: str, type_name: str) -> None:
    """A server of another type would never answer this query: say so, not "timeout"."""
    from components.comm.graph import snapshot
    from components.comm.names import qualify

    qualified = qualify(service, "/")
    info = snapshot(node.session, node.domain).services().get(qualified)  # type: ignore[attr-defined]
    if info is not None and info.servers and type_name not in info.types:
        raise InputError(
            f"service {qualified} is a {', '.join(sorted(info.types))}, not a {type_name}",
            hint="leave the type out to use the one the server declares",
        )


def _servers_near(node: object, service: str) -> str | None:
    """For a call nobody answered: the served names nearest the one called, if any."""
    from components.comm.graph import snapshot
    from components.comm.names import qualify
    from msctl.errors import did_you_mean

    qualified = qualify(service, "/")
    services = snapshot(node.session, node.domain).services()  # type: ignore[attr-defined]
    info = services.get(qualified)
    if info is not None and info.servers:
        return None  # it is served: the server itself did not answer in time
    return did_you_mean(qualified, [name for name, s in services.items() if s.servers]) or None


def _known_service_type(type_name: str) -> None:
    from components.comm.types import registry
    from msctl.errors import did_you_mean

    known = registry().service_names()
    if type_name not in known:
        raise NotFoundError(
            f"unknown service type {type_name!r}",
            hint=did_you_mean(type_name, known) or f"known: {', '.join(known)}",
        )


@app.command("call")
def call(
    service: str = typer.Argument(..., help="Service name, e.g. /limb1/halt."),
    srv_type: str = typer.Argument(None, help="Service type (default: found on the graph)."),
    values: str = typer.Argument(None, help='Request fields as YAML, e.g. "{a: 1, b: 2}".'),
    timeout: float = typer.Option(3.0, "--timeout", help="Seconds to wait for the response."),
    json_output: bool = typer.Option(False, "--json", help="Print the response as JSON."),
) -> None:
    """Call a service once and print its response."""
    from components.comm.services import ServiceError, ServiceTimeout
    from components.comm.types import UnknownTypeError, normalize_type_name
    from msctl.commands.topic import checked_name
    from msctl.console import out, print_json
    from msctl.plane import build_message, connected, find_type, parse_values, to_plain, to_yaml

    checked_name(service, "service")
    if timeout <= 0 or timeout != timeout or timeout == float("inf"):
        raise InputError(f"--timeout must be a positive number of seconds, not {timeout}")
    # Input first, network after: a typo in VALUES or the type fails at once.
    fields = parse_values(values)
    type_name = None
    if srv_type:
        try:
            type_name = normalize_type_name(srv_type)
        except UnknownTypeError as exc:
            raise InputError(str(exc)) from exc
        _known_service_type(type_name)
        build_message(f"{type_name}_Request", fields)
    with connected("service_call") as node:
        if type_name is None:
            type_name = find_type(node, service, "service")
            _known_service_type(type_name)
        else:
            _check_type_on_graph(node, service, type_name)
        client = node.client(service, type_name)
        request = build_message(client.parts.request, fields)
        try:
            response = client.call(request, timeout=timeout)
        except ServiceTimeout as exc:
            raise OperationTimeout(str(exc), hint=_servers_near(node, service)) from exc
        except ServiceError as exc:
            raise NetworkError(str(exc)) from exc
    if json_output:
        print_json(to_plain(response))
    else:
        out.print(to_yaml(response), highlight=False, markup=False)

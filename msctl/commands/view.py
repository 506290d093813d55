"""``msctl view``: the live robot in 3D, on any computer that reaches the assembly.

The picture is composed here, from the lock's URDF and each module's own topics (forward
kinematics at the viewer): nothing new is put on the radio. ``--rerun`` (the default) opens
rerun's desktop window where there is a display (``DISPLAY`` or ``WAYLAND_DISPLAY``), else serves
rerun's web viewer from the installed wheel (no internet, no account) and prints its address;
``--window`` / ``--web`` force either, and a window that cannot open falls back to the web
viewer (:mod:`msctl.view.window`). ``--save FILE.rrd`` also writes everything to a file rerun
opens later.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import typer

from msctl.errors import InputError, MsctlError, NotFoundError

COMMAND_SETTINGS = {"help": "The live robot in 3D (rerun's web viewer, offline); --save FILE.rrd."}

#: What to install for the view.
VIEW_EXTRA = "pip install 'msctl[view]'"


class ViewUnavailable(MsctlError):
    """The view's optional packages are missing. Exit code 2."""

    exit_code = 2


def require_rerun() -> None:
    """Fail with the exact ``pip install`` when rerun-sdk is missing.

    Raises:
        ViewUnavailable: If ``rerun`` cannot be imported.
    """
    try:
        import rerun  # noqa: F401
    except ImportError:
        raise ViewUnavailable(
            "msctl view --rerun needs rerun-sdk, which is not installed",
            hint=f"install the view extra: {VIEW_EXTRA}",
        ) from None


def require_foxglove() -> None:
    """Fail with the exact ``pip install`` when foxglove-sdk is missing.

    Raises:
        ViewUnavailable: If ``foxglove`` cannot be imported.
    """
    try:
        import foxglove  # noqa: F401
    except ImportError:
        raise ViewUnavailable(
            "msctl view --foxglove needs foxglove-sdk, which is not installed",
            hint=f"install the view extra: {VIEW_EXTRA}",
        ) from None


def check_options(rerun: bool, foxglove: bool, save: Path | None, bag: bool = False) -> None:
    """The options shared by ``msctl view`` and ``msctl bag view``.

    Raises:
        InputError: If they contradict each other or ``--save`` cannot be written.
    """
    if rerun and foxglove:
        raise InputError("--rerun and --foxglove cannot be combined: pick one")
    if foxglove and save is not None:
        raise InputError(
            "--save writes rerun's .rrd, not with --foxglove",
            hint="`msctl record` writes a bag Foxglove opens",
        )
    if save is not None:
        if save.suffix != ".rrd":
            raise InputError(f"--save {save}: the file must end in .rrd (rerun's format)")
        if not save.parent.is_dir():
            raise InputError(f"--save {save}: no directory {save.parent}")


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def command(
    rerun: bool = typer.Option(False, "--rerun", help="rerun's web viewer (the default)."),
    foxglove: bool = typer.Option(
        False, "--foxglove", help="A Foxglove WebSocket server on 127.0.0.1 instead."
    ),
    port: int | None = typer.Option(
        None,
        "--port",
        help="rerun's web viewer (default 9090; rerun serves it on every interface, its data "
        "port on 127.0.0.1) or the Foxglove server (default 8765). 0: any free one.",
    ),
    grpc_port: int = typer.Option(
        9876, "--grpc-port", help="Port the viewer reads the data from (0: any free one)."
    ),
    save: Path | None = typer.Option(
        None, "--save", help="Also write everything to this .rrd file (rerun opens it later)."
    ),
    serve: bool = typer.Option(
        True, "--serve/--no-serve", help="--no-serve: only write --save's file, no viewer."
    ),
    window: bool | None = typer.Option(
        None,
        "--window/--web",
        help="rerun's desktop window, or its web viewer (default: the window when DISPLAY or "
        "WAYLAND_DISPLAY is set; the web viewer if the window cannot open).",
        show_default=False,
    ),
    duration: float = typer.Option(0.0, "--for", help="Stop after this many seconds (0: Ctrl-C)."),
) -> None:
    """Show the running assembly in 3D: its composed URDF, every joint from its module's
    joint_read, limb tips and IK targets, health as colour, alarms, claims and halts. The
    address to open is printed on stdout."""
    check_options(rerun, foxglove, save)
    if duration < 0:
        raise InputError(f"--for must be 0 or more seconds, not {duration}")
    if not serve and save is None:
        raise InputError("--no-serve shows nothing: give --save FILE.rrd too")
    port = (8765 if foxglove else 9090) if port is None else port
    for name, value in (("--port", port), ("--grpc-port", grpc_port)):
        if not 0 <= value <= 65535:
            raise InputError(f"{name} must be a TCP port (0-65535), not {value}")
    if foxglove:
        require_foxglove()
        _serve_foxglove(port, duration)
        return
    require_rerun()

    from components.assembly import AssemblyError, load_assembly
    from msctl.console import err
    from msctl.plane import connected
    from msctl.view.live import LiveView
    from msctl.view.rerun_sink import RerunSink
    from msctl.view.scene import SceneError, scene_of
    from msctl.view.window import Showing

    try:
        assembly = load_assembly()
        scene = scene_of(assembly)
    except (AssemblyError, SceneError) as exc:
        raise NotFoundError(str(exc)) from exc
    scene.changes()  # poses at zero: the camera's first framing
    grpc = (grpc_port or free_port()) if serve else None
    stop = _stop_on_signals()
    with connected("view") as node:
        sink = RerunSink(save=save, serve=grpc, recording_name=assembly.template, eye=scene.eye())
        shown = Showing(sink, window, port, assembly.template)
        try:
            if serve:
                shown.open()
            with LiveView(node, assembly, scene, sink) as live:
                err.print(f"following {len(live.topics)} topics, health and claims", style="dim")
                until = _until(stop, duration)
                live.run(lambda: shown.closed() or until())
        finally:
            shown.close()
            sink.close()
    if save is not None:
        err.print(f"saved {save}", highlight=False)


def _serve_foxglove(port: int, duration: float) -> None:
    from components.assembly import AssemblyError, load_assembly
    from msctl.console import err, out
    from msctl.plane import connected
    from msctl.view.foxglove_server import FoxgloveView
    from msctl.view.scene import SceneError, scene_of

    try:
        assembly = load_assembly()
        scene = scene_of(assembly)
    except (AssemblyError, SceneError) as exc:
        raise NotFoundError(str(exc)) from exc
    stop = _stop_on_signals()
    with connected("view") as node, FoxgloveView(node, assembly, scene, port=port) as server:
        url = f"ws://127.0.0.1:{server.port}"
        out.print(url, highlight=False, soft_wrap=True)
        err.print(
            f"serving {assembly.template} to Foxglove: open a connection to {url} (Ctrl-C to stop)"
        )
        err.print(f"following {len(server.topics)} topics", style="dim")
        server.run(_until(stop, duration))


def _stop_on_signals():
    import signal
    import threading

    stop = threading.Event()

    def handler(_signum, _frame) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


def _until(stop, duration: float):
    import time

    deadline = time.monotonic() + duration if duration else None
    return lambda: stop.is_set() or (deadline is not None and time.monotonic() >= deadline)


def view_bag(
    bag: Path,
    save: Path | None,
    port: int,
    grpc_port: int,
    serve: bool,
    duration: float,
    window: bool | None = None,
) -> None:
    """``msctl bag view``: a bag's picture on rerun's timeline (:mod:`msctl.view.bag`).

    The bag is read whole into the recording, then the viewer serves it until Ctrl-C (or
    ``duration`` seconds); with ``--no-serve`` it only writes ``save``.
    """
    if duration < 0:
        raise InputError(f"--for must be 0 or more seconds, not {duration}")
    if not serve and save is None:
        raise InputError("--no-serve shows nothing: give --save FILE.rrd too")
    require_rerun()

    from msctl.console import err
    from msctl.view.bag import draw_bag
    from msctl.view.rerun_sink import RerunSink
    from msctl.view.window import Showing

    assembly, scene = _bag_assembly()
    scene.changes()
    grpc = (grpc_port or free_port()) if serve else None
    sink = RerunSink(save=save, serve=grpc, recording_name=bag.name, eye=scene.eye())
    shown = Showing(sink, window, port, bag.name)
    try:
        with _reading(bag) as advance:
            report = draw_bag(bag, assembly, scene, sink, advance)
        for module in report.unknown_modules:
            err.print(
                f"[yellow]{bag}: /{module} was recorded but {assembly.template} has no such "
                "module: not drawn[/]"
            )
        if not report.messages:
            err.print(f"[yellow]{bag}: none of {assembly.template}'s modules' topics in it[/]")
        err.print(
            f"{bag}: {report.messages:,} messages drawn over {report.end - report.start:.1f} s",
            highlight=False,
        )
        if serve:
            shown.open()
            stop = _stop_on_signals()
            import time

            until = _until(stop, duration)
            while not (shown.closed() or until()):
                time.sleep(0.2)
    finally:
        shown.close()
        sink.close()
    if save is not None:
        err.print(f"saved {save}", highlight=False)


def view_bag_foxglove(bag: Path, port: int, duration: float) -> None:
    """``msctl bag view --foxglove``: a bag played to Foxglove over its time range
    (:mod:`msctl.view.bag_foxglove`); Foxglove's playback bar plays, pauses, seeks and sets
    the speed. Serves until Ctrl-C (or ``duration`` seconds)."""
    if duration < 0:
        raise InputError(f"--for must be 0 or more seconds, not {duration}")
    if not 0 <= port <= 65535:
        raise InputError(f"--port must be a TCP port (0-65535), not {port}")
    require_foxglove()

    from msctl.console import err, out
    from msctl.view.bag_foxglove import BagFoxglove, read_bag

    assembly, scene = _bag_assembly()
    with _reading(bag) as advance:
        recorded = read_bag(bag, advance)
    for topic in recorded.fixed:
        err.print(
            f"[yellow]{bag}: {topic}'s schema names its dependencies pkg/msg/Type: "
            "sent in rosbag2's form (`msctl bag recover --fix-schemas` fixes the bag)[/]"
        )
    for topic in recorded.left_out:
        err.print(f"[yellow]{bag}: its own {topic} is not sent: the view composes {topic}[/]")
    seconds = (recorded.end - recorded.start) / 1e9
    err.print(
        f"{bag}: {len(recorded.messages):,} messages on {len(recorded.definitions)} topics "
        f"over {seconds:.1f} s",
        highlight=False,
    )
    stop = _stop_on_signals()
    with BagFoxglove(recorded, assembly, scene, port=port) as player:
        url = f"ws://127.0.0.1:{player.port}"
        out.print(url, highlight=False, soft_wrap=True)
        err.print(
            f"playing {bag.name} to Foxglove: open a connection to {url}; its playback bar "
            "plays, pauses, seeks (Ctrl-C to stop)"
        )
        player.run(_until(stop, duration))


def _bag_assembly() -> tuple[Any, Any]:
    """This computer's resolved assembly and its scene, with which a bag is drawn.

    Raises:
        NotFoundError: If there is none, or it cannot be drawn.
    """
    from components.assembly import AssemblyError, load_assembly
    from msctl.view.scene import SceneError, scene_of

    try:
        assembly = load_assembly()
        return assembly, scene_of(assembly)
    except (AssemblyError, SceneError) as exc:
        raise NotFoundError(
            f"{exc}", hint="a bag is drawn with this computer's resolved assembly"
        ) from exc


@contextlib.contextmanager
def _reading(bag: Path) -> Iterator[Callable[[float], None]]:
    """A progress bar while ``bag`` is read; yields what to call with the share done."""
    from rich.progress import BarColumn, Progress, TextColumn

    from msctl.console import err

    with Progress(
        TextColumn("reading {task.description}"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        console=err,
        transient=True,
        disable=not err.is_terminal,
    ) as progress:
        task = progress.add_task(bag.name, total=1.0)
        yield lambda done: progress.update(task, completed=done)

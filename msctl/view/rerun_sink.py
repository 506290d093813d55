"""Draws a :class:`~msctl.view.scene.Scene` with rerun: its web viewer served from the wheel
(no internet, no account), and/or an ``.rrd`` file.

Entities:

* ``robot/<slot>/<link>``: the link's pose in the world (``Transform3D``), its shapes below it
  (``.../visual_<i>``: boxes, cylinders, spheres, meshes), tinted by the module's health level;
* ``targets/<slot>/tip`` and ``targets/<slot>/ik_target``: a limb's tip and IK target;
* ``cmd_vel``: the commanded twist of a mobile assembly, as an arrow at its root;
* ``twist/<slot>``: each wheel module's commanded twist (from its ``joint_set``), as an arrow
  at the module, labelled with its speed and turn rate;
* ``status``: one line per module (level, on the graph, halted, who holds its claim);
* ``alarms``: every level change, claim and module arriving or leaving, as a text log.

Time is the ``time`` timeline (the sample's wall clock, live or recorded), so a bag's picture
scrubs on rerun's timeline.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import quote

from msctl.view.scene import LEVEL_COLOURS, Changes, Pose, Scene, Shape
from msctl.view.wheels import WheelTwist

Vec = tuple[float, float, float]

#: The timeline every sample is put on.
TIMELINE = "time"
#: The application id rerun shows.
APPLICATION = "msctl_view"

_TEXT_LEVELS = {"OK": "INFO", "WARN": "WARN", "ERROR": "ERROR", "STALE": "WARN"}


def blueprint(eye: tuple[Vec, Vec] | None = None) -> Any:
    """The layout: the 3D robot large, the module status and the alarm log beside it.

    Args:
        eye: Where the camera starts and what it looks at (the whole assembly in sight).
    """
    import rerun.blueprint as rrb

    controls = None
    if eye is not None:
        controls = rrb.EyeControls3D(position=eye[0], look_target=eye[1], eye_up=(0, 0, 1))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(
                name="robot",
                origin="/",
                contents=["+ /robot/**", "+ /targets/**", "+ /cmd_vel", "+ /twist/**"],
                eye_controls=controls,
            ),
            rrb.Vertical(
                rrb.TextDocumentView(name="modules", origin="/status"),
                rrb.TextLogView(name="alarms", origin="/alarms"),
            ),
            column_shares=[3, 1],
        ),
        rrb.TimePanel(state="collapsed"),
        collapse_panels=True,
    )


def mesh_path(uri: str) -> Path | None:
    """The file of a URDF mesh (``package://msctl/...``, ``file://...`` or a path), if it exists.

    A mesh that cannot be found is drawn as a point (and the URDF named by ``msctl assemble``'s
    checks is where to fix it).
    """
    from msctl.view.foxglove_server import PACKAGE_ROOT

    if uri.startswith("package://msctl/"):
        path = PACKAGE_ROOT / uri[len("package://msctl/") :]
    elif uri.startswith("file://"):
        path = Path(uri[len("file://") :])
    else:
        path = Path(uri)
    return path if path.is_file() else None


class RerunSink:
    """One rerun recording fed from a scene.

    Args:
        save: Also write everything to this ``.rrd`` file.
        serve: Serve the recording over gRPC on this port (the web viewer connects to it).
        recording_name: What rerun names the recording (the assembly).
        eye: Where the camera starts and what it looks at.
    """

    def __init__(
        self,
        save: Path | None = None,
        serve: int | None = None,
        recording_name: str = "",
        eye: tuple[Vec, Vec] | None = None,
    ) -> None:
        import rerun as rr

        self.rr = rr
        self.recording = rr.RecordingStream(APPLICATION, make_default=False)
        if recording_name:
            self.recording.send_recording_name(recording_name)
        sinks: list[Any] = []
        if serve is not None:
            sinks.append(rr.GrpcServerSink(bind_ip="127.0.0.1", port=serve))
        if save is not None:
            sinks.append(rr.FileSink(str(save)))
        self.grpc_port = serve
        if sinks:
            self.recording.set_sinks(*sinks, default_blueprint=blueprint(eye))
        self._shapes: dict[str, list[tuple[str, Shape]]] = {}
        self._status: dict[str, str] = {}

    @property
    def grpc_url(self) -> str:
        """Where a viewer reads the recording (``rerun+http://127.0.0.1:PORT/proxy``)."""
        return f"rerun+http://127.0.0.1:{self.grpc_port}/proxy"

    def serve_web_viewer(self, port: int) -> str:
        """Serve rerun's web viewer (from the wheel) on 127.0.0.1; return its address."""
        self.rr.serve_web_viewer(web_port=port, open_browser=False, connect_to=self.grpc_url)
        return f"http://127.0.0.1:{port}/?url={quote(self.grpc_url, safe='')}"

    def _log(self, path: str, *archetypes: Any, static: bool = False) -> None:
        self.recording.log(path, *archetypes, static=static)

    def at(self, seconds: float) -> None:
        """Put what follows at ``seconds`` (Unix time) on the timeline."""
        self.recording.set_time(TIMELINE, timestamp=seconds)

    def at_ns(self, nanoseconds: int) -> None:
        """Put what follows at a recorded time (ns since the epoch), to the nanosecond."""
        import numpy as np

        self.recording.set_time(TIMELINE, timestamp=np.datetime64(nanoseconds, "ns"))

    def draw_shapes(self, scene: Scene) -> None:
        """Every link's shapes, once, in its module's present colour."""
        self._log("/", self.rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for look in scene.links:
            entity = f"robot/{look.module or 'assembly'}/{look.link}"
            paths = self._shapes.setdefault(look.module, [])
            for i, shape in enumerate(look.shapes):
                paths.append((f"{entity}/visual_{i}", shape))
        for module, state in scene.modules.items():
            self.tint(module, state.look)
        self.tint("", "OK")

    def tint(self, module: str, look: str) -> None:
        """Draw a module's shapes in the colour of ``look`` (a key of :data:`LEVEL_COLOURS`)."""
        colour = LEVEL_COLOURS.get(look, LEVEL_COLOURS["OK"])
        for path, shape in self._shapes.get(module, ()):
            self._log(path, self._archetype(shape, colour))

    def _archetype(self, shape: Shape, colour: tuple[int, int, int, int]) -> Any:
        draw = _SHAPES.get(shape.kind, _mesh)
        return draw(self.rr, shape, colour)

    def draw(self, scene: Scene, changes: Changes) -> None:
        """What :meth:`Scene.changes` said: link poses, module colours, status, markers."""
        rr = self.rr
        modules = {look.link: look.module or "assembly" for look in scene.links}
        for link, pose in changes.poses.items():
            self._log(f"robot/{modules.get(link, 'assembly')}/{link}", _transform(rr, pose))
        for module, look in changes.looks.items():
            self.tint(module, look)
        if changes.status:
            # One document: a text view shows one, and a glance should take in every module.
            self._status.update(changes.status)
            text = "\n".join(f"- {line}" for _, line in sorted(self._status.items()))
            self._log("status", rr.TextDocument(text, media_type="text/markdown"))
        for slot, twist in changes.twists.items():
            self.twist(slot, twist)
        for name, pose in changes.markers.items():
            # A limb's tip green, an IK target (what it was asked to reach) magenta.
            colour = _MARKER_COLOURS.get(name.rsplit("/", 1)[-1], _TARGET_COLOUR)
            self._log(
                f"targets/{name}",
                rr.Points3D([pose[0]], radii=[0.02], colors=[colour], labels=[name]),
            )

    def twist(self, slot: str, twist: WheelTwist) -> None:
        """A wheel module's commanded twist: an arrow of its velocity (m/s) at its wheels."""
        self._log(
            f"twist/{slot}",
            self.rr.Arrows3D(
                origins=[twist.origin],
                vectors=[twist.linear],
                colors=[_TWIST_COLOUR],
                labels=[twist.label(slot)],
            ),
        )

    def arrow(self, origin: tuple[float, float, float], vector: tuple[float, float, float]) -> None:
        """The commanded twist of the assembly (m/s) as an arrow at its root."""
        self._log(
            "cmd_vel",
            self.rr.Arrows3D(origins=[origin], vectors=[vector], colors=[(40, 140, 250, 255)]),
        )

    def say(self, text: str, level: str = "INFO") -> None:
        """One line in the alarm log (``level``: a health level or a rerun text level)."""
        self._log("alarms", self.rr.TextLog(text, level=_TEXT_LEVELS.get(level, level)))

    def close(self) -> None:
        """Flush and detach every sink (the ``.rrd`` file is complete afterwards)."""
        try:
            self.recording.flush()
        finally:
            self.recording.disconnect()


def _transform(rr: Any, pose: Pose) -> Any:
    translation, quaternion = pose
    return rr.Transform3D(translation=translation, quaternion=quaternion)


Colour = tuple[int, int, int, int]


def _box(rr: Any, shape: Shape, colour: Colour) -> Any:
    (x, y, z), quaternion = shape.origin
    return rr.Boxes3D(
        sizes=[shape.size],
        centers=[(x, y, z)],
        quaternions=[quaternion],
        colors=[colour],
        fill_mode="solid",
    )


def _cylinder(rr: Any, shape: Shape, colour: Colour) -> Any:
    (x, y, z), quaternion = shape.origin
    radius, length = shape.size
    return rr.Cylinders3D(
        lengths=[length],
        radii=[radius],
        centers=[(x, y, z)],
        quaternions=[quaternion],
        colors=[colour],
        fill_mode="solid",
    )


def _sphere(rr: Any, shape: Shape, colour: Colour) -> Any:
    (x, y, z), _ = shape.origin
    return rr.Ellipsoids3D(
        half_sizes=[(shape.size[0],) * 3],
        centers=[(x, y, z)],
        colors=[colour],
        fill_mode="solid",
    )


def _mesh(rr: Any, shape: Shape, colour: Colour) -> Any:
    """A mesh file as an asset; a point where the file cannot be found."""
    path = mesh_path(shape.mesh)
    if path is None:
        return rr.Points3D([shape.origin[0]], colors=[colour], radii=[0.01])
    return rr.Asset3D(path=path, albedo_factor=colour)


#: A URDF geometry's kind -> how rerun draws it (anything else is a mesh).
_SHAPES: dict[str, Callable[[Any, Shape, Colour], Any]] = {
    "box": _box,
    "cylinder": _cylinder,
    "sphere": _sphere,
}
#: A marker's last name chunk -> its colour; the rest are IK targets.
_MARKER_COLOURS: dict[str, Colour] = {"tip": (60, 200, 90, 255)}
_TARGET_COLOUR: Colour = (230, 120, 230, 255)
#: A wheel module's commanded twist (the assembly's cmd_vel arrow is a darker blue).
_TWIST_COLOUR: Colour = (60, 200, 230, 255)

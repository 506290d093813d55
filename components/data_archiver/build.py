"""Build a data archiver from the resolved assembly, and start its recording when bound.

The core only reports; the recording is the recorder of ``msctl record``
(:class:`components.recording.recorder.Recorder`), started by the ``on_bound`` hook on the
executor's session, as the component's node, so the graph shows its subscriptions under
the archiver's name. It is stopped, and its bag closed, with the component's resources.

Where: one bag per start, ``<directory>/<station>_<node>_<date-time>``, with ``directory``
relative to msctl's state directory (``$MSCTL_HOME``) unless absolute.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from components.assembly import ComponentPlan, ResolvedAssembly, state_dir
from components.build import BuiltComponent, config_from_params, node_name
from components.data_archiver.core import (
    ArchiverConfig,
    DataArchiverCore,
    RecorderStatus,
    bag_name,
    params_of,
)
from components.data_archiver.interface import DATA_ARCHIVER

if TYPE_CHECKING:
    from components.executor.executor import Component, Executor


class Recording:
    """The archiver's recording: started on the executor's session, stopped on close.

    Args:
        config: The archiver's parameters.
        directory: The bag directory to create.
    """

    def __init__(self, config: ArchiverConfig, directory: Path) -> None:
        self.config = config
        self.directory = directory
        self._recorder: Any = None
        self._lock = threading.Lock()
        self._error = ""

    def __call__(self, executor: Executor, component: Component) -> None:
        """Start recording as ``component``'s node (called once, before it runs)."""
        from components.recording.errors import BagError
        from components.recording.recorder import Recorder
        from components.recording.thinned import radio_thinned

        if executor.transport != "zenoh":
            # The recorder reads Zenoh keys and tokens; on rclpy the data is on DDS.
            self._error = (
                f"the data archiver records msctl's Zenoh data plane, and this process runs on "
                f"{executor.transport}: record the ROS graph with `ros2 bag record`, or run "
                "the components on Zenoh (unset MSCTL_TRANSPORT)"
            )
            return
        try:
            self.directory.parent.mkdir(parents=True, exist_ok=True)
            recorder = Recorder(
                executor.session,
                self.directory,
                self.config.selection(),
                domain=component.node.domain,
                node=component.node,
                thinned=radio_thinned(),
                **params_of(self.config),
            )
            recorder.start()
        except (BagError, OSError) as exc:
            # Reported on diagnostics (ERROR), where the station's operator looks.
            self._error = f"cannot record into {self.directory}: {exc}"
            return
        with self._lock:
            self._recorder = recorder

    def status(self) -> RecorderStatus:
        """The recording's status (an error status if it never started)."""
        with self._lock:
            recorder = self._recorder
        if recorder is None:
            return RecorderStatus(directory=str(self.directory), error=self._error)
        return recorder.status()

    def close(self) -> None:
        """Stop recording and finish the bag (idempotent)."""
        with self._lock:
            recorder, self._recorder = self._recorder, None
        if recorder is not None:
            try:
                recorder.stop()
            except Exception as exc:  # the bag stays recoverable; say so in the log
                import logging

                logging.getLogger(__name__).error("data archiver: %s", exc)


def bag_directory(config: ArchiverConfig, plan: ComponentPlan, now: datetime) -> Path:
    """Where a start of this archiver records."""
    root = Path(config.directory).expanduser()
    if not root.is_absolute():
        root = state_dir() / root
    return root / bag_name(plan.name, now.strftime("%Y_%m_%d-%H_%M_%S"))


def build(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any]
) -> BuiltComponent:
    """A data archiver recording what ``plan``'s parameters say.

    Params: :class:`ArchiverConfig` fields.

    Raises:
        BuildError: If a parameter is out of range or a pattern does not compile.
    """
    del assembly, options
    config = config_from_params(plan, ArchiverConfig)
    recording = Recording(config, bag_directory(config, plan, datetime.now()))
    core = DataArchiverCore(plan.name, recording.status, hardware_id=plan.host)
    built = BuiltComponent(core, DATA_ARCHIVER, plan.namespace, node_name(plan.name))
    built.resources.append(recording)
    built.on_bound = recording
    return built

"""doit as msctl runs it: its own plugins only, and its events turned into the builder's."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from msctl.workspace.build import Builder


@contextmanager
def without_entry_point_plugins() -> Iterator[None]:
    """Run doit with its own commands, backends and reporters only.

    doit adds plugins from every installed distribution's ``doit.*`` entry points, and a
    plugin there takes precedence over doit's own of the same name (a ``json`` backend, a
    reporter): what the environment happens to hold must not change how msctl builds. It
    also reads every distribution's entry points three times per run, most of a no-op
    build's time in a large environment.
    """
    import doit.plugin

    original = doit.plugin.entry_points_impl
    doit.plugin.entry_points_impl = lambda: lambda group: ()  # type: ignore[assignment]
    try:
        yield
    finally:
        doit.plugin.entry_points_impl = original


class Reporter:
    """doit's reporter for msctl: turns doit's events into :meth:`Builder._event` calls.

    doit calls it from its worker threads (``execute_task``) and its main loop (the rest).
    """

    desc = "msctl build events"

    def __init__(self, builder: Builder):
        self.builder = builder
        self.errors: list[str] = []

    def initialize(self, tasks: Any, selected_tasks: Any) -> None:
        """Tasks are loaded."""

    def get_status(self, task: Any) -> None:
        """A task's up-to-date check starts."""

    def execute_task(self, task: Any) -> None:
        """A task starts running."""
        self.builder._event(task.name, "building")

    def add_success(self, task: Any) -> None:
        """A task ran successfully."""
        self.builder._event(task.name, "built")

    def add_failure(self, task: Any, fail: Any) -> None:
        """A task failed, or could not run because a dependency failed."""
        from doit.exceptions import UnmetDependency

        if isinstance(fail, UnmetDependency):
            failed = [
                n.split(":", 1)[1] if n.startswith("build:") else n
                for n in str(fail.message).split()
            ]
            packages = self.builder.graph.packages
            names = [packages[k].name if k in packages else k for k in failed]
            self.builder._event(task.name, "blocked", f"not built: {', '.join(names)} failed")
        else:
            self.builder._event(task.name, "failed", fail.get_msg().strip().splitlines()[0])

    def skip_uptodate(self, task: Any) -> None:
        """A task was up to date."""
        self.builder._event(task.name, "up to date")

    def skip_ignore(self, task: Any) -> None:
        """A task was ignored (never, here)."""

    def cleanup_error(self, exception: Any) -> None:
        """A teardown failed (there are none here)."""
        self.errors.append(str(exception))

    def runtime_error(self, msg: str) -> None:
        """doit itself failed."""
        self.errors.append(msg)

    def teardown_task(self, task: Any) -> None:
        """A teardown starts (there are none here)."""

    def complete_run(self) -> None:
        """Everything ran."""

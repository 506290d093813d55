"""What ``msctl build`` reports: each package's result and the build's outcome."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

#: What a package's build ended as.
STATUSES = ("built", "up to date", "failed", "blocked", "skipped", "not run")


@dataclass
class PackageResult:
    """What became of one package.

    Attributes:
        name: The package.
        type: ``python``, ``ros`` or ``command``.
        status: One of :data:`STATUSES`.
        step: The step that failed (or why it was skipped or blocked).
        message: The failure's last log lines, or the reason.
        log: Its build log.
        seconds: How long its build took.
    """

    name: str
    type: str
    status: str = "not run"
    step: str = ""
    message: str = ""
    log: str | None = None
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """The result as ``--json`` prints it."""
        return asdict(self)


@dataclass
class BuildResult:
    """The outcome of one ``msctl build``.

    Attributes:
        workspace: The workspace directory.
        packages: Each selected package's result, in build order.
        wheelhouse: The wheelhouse task's result, when there is one.
        seconds: Wall time of the whole build.
        errors: Errors of doit itself (not of a package).
        notes: What the build did beyond building (its state rebuilt, say), one line each.
        stopped: Why the build was stopped before its end (``""``: it was not).
    """

    workspace: Path
    packages: list[PackageResult]
    wheelhouse: PackageResult | None = None
    seconds: float = 0.0
    errors: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    stopped: str = ""

    @property
    def ok(self) -> bool:
        """Whether nothing failed or was blocked."""
        bad = {"failed", "blocked", "not run"}
        return (
            not self.errors
            and not self.stopped
            and all(p.status not in bad for p in self.packages)
            and (self.wheelhouse is None or self.wheelhouse.status not in bad)
        )

    @property
    def nothing_done(self) -> bool:
        """Whether every package was up to date (and no download ran)."""
        return all(p.status in ("up to date", "skipped") for p in self.packages) and (
            self.wheelhouse is None or self.wheelhouse.status == "up to date"
        )

    def to_dict(self) -> dict[str, Any]:
        """The result as ``--json`` prints it."""
        return {
            "workspace": str(self.workspace),
            "ok": self.ok,
            "nothing_done": self.nothing_done,
            "seconds": round(self.seconds, 3),
            "packages": [p.to_dict() for p in self.packages],
            "wheelhouse": self.wheelhouse.to_dict() if self.wheelhouse else None,
            "errors": self.errors,
            "notes": self.notes,
            "stopped": self.stopped,
        }

"""The agent's side of ``msctl update --all`` and ``msctl build --all``: the workspace
requests as typed structs, checked as data, and the worker that carries out one job at a
time (see :mod:`msctl.workspace.remote` for the ground station's side and the protocol).

Each ``msctl agent`` serves ``/msctl/<host>/workspace`` (``msctl_msgs/srv/AgentRequest``,
the supervisors' request type, :mod:`components.supervision`) beside its ``/request``.
"""

from __future__ import annotations

import json
import os
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import msgspec

from components.supervision.contract import RequestError
from components.supervision.protocol import Checked
from msctl.errors import MsctlError

SERVICE = "workspace"
#: A request's arguments, at most: a workspace file and its overlays are a few KiB each.
MAX_ARGS_BYTES = 512 * 1024
MAX_OVERLAYS = 16
MAX_PACKAGES = 256
_FILE_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.+-]{0,99}$")
PackageName = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")]


class Refused(RequestError):
    """A workspace request refused; the message says why."""


class _Request(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """What every workspace request is: a struct tagged by its verb, with no unknown field."""


class Update(_Request, tag="update", tag_field="verb"):
    """Put the workspace on the versions of ``repos`` and its ``overlays``."""

    repos: Any = None
    overlays: Annotated[list[Any], msgspec.Meta(max_length=MAX_OVERLAYS)] = []
    offline: bool = False
    shallow: bool = False


class Build(_Request, tag="build", tag_field="verb"):
    """Build the workspace (only what ``packages_up_to`` needs, if given)."""

    packages_up_to: Annotated[list[PackageName], msgspec.Meta(max_length=MAX_PACKAGES)] = []
    offline: bool = False


class Progress(_Request, tag="progress", tag_field="verb"):
    """What the running (or last) job has done so far."""


#: Each workspace request's struct by its verb.
REQUESTS: dict[str, type[_Request]] = {
    cls.__struct_config__.tag: cls  # type: ignore[misc]
    for cls in _Request.__subclasses__()
}
VERBS = tuple(REQUESTS)
#: What a value that does not fit its field is told, by field.
_FIELD_RULES = {
    "offline": "offline must be true or false",
    "shallow": "shallow must be true or false",
    "overlays": f"overlays must be a list of at most {MAX_OVERLAYS} files",
    "packages_up_to": "packages_up_to must be a list of plain package names",
}
_FIELD = re.compile(r"`\$\.([A-Za-z_]+)")


def check_request(verb: Any, args_text: Any) -> dict[str, Any]:
    """Validate a workspace request: its verb, and arguments that are data only.

    Returns:
        The arguments, with ``repositories`` (the merged files, checked) for an update.

    Raises:
        Refused: Naming what is wrong.
    """
    request = parse(verb, args_text).request
    args = msgspec.to_builtins(request)
    del args["verb"]
    if isinstance(request, Update):
        from msctl.workspace.repos import load_texts

        base = _file(request.repos, "repos")
        files = [_file(o, f"overlays[{i}]") for i, o in enumerate(request.overlays)]
        try:
            args["repositories"] = load_texts(base, files)
        except MsctlError as exc:
            raise Refused(f"the files sent are refused: {exc}") from None
    return args


def parse(verb: Any, args_text: Any) -> Checked:
    """A workspace request's struct, from its verb and its arguments' JSON text.

    Raises:
        Refused: For an unknown verb, text too big or not a JSON object, unknown keys or
            bad values.
    """
    if not isinstance(verb, str) or verb not in REQUESTS:
        shown = verb[:40] if isinstance(verb, str) else type(verb).__name__
        raise Refused(f"unknown verb {shown!r}; accepted: {', '.join(VERBS)}")
    if not isinstance(args_text, str):
        raise Refused("arguments must be JSON text")
    if (
        len(args_text) > MAX_ARGS_BYTES
        or len(args_text.encode("utf-8", "replace")) > MAX_ARGS_BYTES
    ):
        raise Refused(f"arguments are over {MAX_ARGS_BYTES} bytes")
    try:
        args = json.loads(args_text) if args_text.strip() else {}
    except (ValueError, RecursionError) as exc:
        raise Refused(f"arguments are not JSON: {str(exc)[:200]}") from None
    if not isinstance(args, dict):
        raise Refused("arguments must be a JSON object")
    cls = REQUESTS[verb]
    unknown = set(args) - set(cls.__struct_fields__)
    if unknown:
        raise Refused(f"{verb} takes no argument {', '.join(sorted(map(str, unknown)))}")
    try:
        request = msgspec.convert({**args, "verb": verb}, cls)
    except msgspec.ValidationError as exc:
        where = _FIELD.search(str(exc))
        rule = _FIELD_RULES.get(where.group(1)) if where else None
        raise Refused(rule or f"{verb}: {exc}") from None
    return Checked(verb, args, request)  # type: ignore[arg-type]


def _file(value: Any, where: str) -> tuple[str, str]:
    if not isinstance(value, dict) or set(value) != {"name", "text"}:
        raise Refused(f"{where} must be an object with a file's name and text")
    name, text = value["name"], value["text"]
    if not isinstance(name, str) or not _FILE_NAME.match(name) or ".." in name:
        raise Refused(f"{where}: file name {str(name)[:60]!r} is not a plain file name")
    if not isinstance(text, str):
        raise Refused(f"{where}: the file's text must be a string")
    return name, text


# --------------------------------------------------------------------------- the agent's side
class WorkspaceAgent:
    """Updates and builds this computer's workspace when a ground station asks.

    Args:
        host: This computer's name (its service is ``/msctl/<host>/workspace``).
        workspace: The workspace directory (the agent's own setting).
        wheelhouse: Where an offline build installs external wheels from (its own setting).
        log: Where to say what it does (one line per call).
    """

    def __init__(
        self,
        host: str,
        workspace: Path,
        wheelhouse: Path | None = None,
        log: Callable[[str], None] | None = None,
    ):
        self.host = host
        self.workspace = workspace
        self.wheelhouse = wheelhouse
        self._log = log or (lambda _line: None)
        self._lock = threading.Lock()
        self._job: dict[str, Any] | None = None
        self._thread: threading.Thread | None = None
        self._count = 0
        self.node: Any = None

    @classmethod
    def from_env(cls, host: str, log: Callable[[str], None] | None = None) -> WorkspaceAgent:
        """The agent's settings from its environment: ``MSCTL_WORKSPACE`` (default
        ``$MSCTL_HOME/workspace``) and ``MSCTL_WHEELHOUSE``."""
        from components.assembly import state_dir

        given = os.environ.get("MSCTL_WORKSPACE")
        workspace = Path(given) if given else state_dir() / "workspace"
        wheelhouse = os.environ.get("MSCTL_WHEELHOUSE")
        return cls(host, workspace.absolute(), Path(wheelhouse) if wheelhouse else None, log)

    # ------------------------------------------------------------------ serving
    def serve(self, session: Any, domain: int) -> None:
        """Serve ``/msctl/<host>/workspace`` on ``session``."""
        from components.comm.node import Node
        from components.supervision.contract import AGENT_SRV, host_namespace

        self.node = Node(session, "workspace", host_namespace(self.host), domain)
        self.node.service(SERVICE, AGENT_SRV, self._on_request, deferred=True)
        self._log(f"serving {self.node.namespace}/{SERVICE} for {self.workspace}")

    def close(self, wait: float = 5.0) -> None:
        """Stop serving, and give a running job ``wait`` seconds to end (each repository's
        update is whole or nothing, so one cut short is left as it was)."""
        if self.node is not None:
            self.node.close()
            self.node = None
        thread = self._thread
        if thread is not None:
            thread.join(wait)

    def _on_request(self, pending: Any) -> None:
        from components.supervision.dispatch import reply

        verb = getattr(getattr(pending, "request", None), "verb", "?")
        try:
            payload, message = self.handle(pending.request.verb, pending.request.args)
            reply(pending, True, message, payload)
        except Refused as exc:
            self._log(f"refused workspace {str(verb)[:40]!r}: {exc}")
            reply(pending, False, str(exc))
        except Exception as exc:  # an error reply, never the agent's end
            self._log(f"workspace request {str(verb)[:40]!r} failed: {exc}")
            reply(pending, False, f"{self.host} could not {verb}: {type(exc).__name__}: {exc}")

    # ------------------------------------------------------------------ requests
    def handle(self, verb: Any, args_text: Any) -> tuple[dict[str, Any], str]:
        """Carry out one request; returns ``(payload, message)``.

        Raises:
            Refused: For a malformed request, or a job while another runs.
        """
        args = check_request(verb, args_text)
        if verb == "progress":
            return self.progress(), "ok"
        with self._lock:
            if self._job is not None and self._job["state"] == "running":
                raise Refused(
                    f"{self.host} is already running {self._job['verb']} (job "
                    f"{self._job['id']}, for {time.time() - self._job['started']:.0f} s)"
                )
            self._count += 1
            self._job = {
                "id": self._count,
                "verb": verb,
                "state": "running",
                "started": time.time(),
                "items": {},
                "result": None,
                "error": "",
            }
            job = self._job
        work = self._update if verb == "update" else self._build
        self._thread = threading.Thread(
            target=self._run, args=(job, work, args), name=f"msctl-{verb}", daemon=True
        )
        self._thread.start()
        self._log(f"{verb} started (job {job['id']}) in {self.workspace}")
        return self.progress(), f"{verb} started"

    def progress(self) -> dict[str, Any]:
        """The running (or last) job, as the ground station shows it."""
        with self._lock:
            job = json.loads(json.dumps(self._job)) if self._job else None
        return {"host": self.host, "workspace": str(self.workspace), "job": job}

    def _set(self, job: dict[str, Any], name: str, stage: str) -> None:
        with self._lock:
            job["items"][name] = stage

    def _run(self, job: dict[str, Any], work: Callable[..., Any], args: dict[str, Any]) -> None:
        try:
            result, ok = work(job, args)
            error = ""
        except MsctlError as exc:
            result, ok, error = None, False, str(exc)
        except Exception as exc:
            result, ok, error = None, False, f"{type(exc).__name__}: {exc}"
        with self._lock:
            job.update(state="done", result=result, ok=ok, error=error)
        self._log(f"{job['verb']} done (job {job['id']}): {'ok' if ok else error or 'failed'}")

    def _update(self, job: dict[str, Any], args: dict[str, Any]) -> tuple[Any, bool]:
        from msctl.workspace import state_dir, workspace_lock
        from msctl.workspace.update import (
            UpdateOptions,
            remember_files,
            update_workspace,
            write_atomically,
        )

        repositories = args["repositories"]
        for repo in repositories:
            self._set(job, repo.path, "waiting")
        options = UpdateOptions(
            offline=args.get("offline", False), shallow=args.get("shallow", False)
        )
        self.workspace.mkdir(parents=True, exist_ok=True)
        with workspace_lock(self.workspace, "update"):
            # The files as sent, kept: `msctl update --status` on the robot reads them.
            sent = state_dir(self.workspace) / "sent"
            names = [args["repos"]["name"], *(o["name"] for o in args.get("overlays", []))]
            texts = [args["repos"]["text"], *(o["text"] for o in args.get("overlays", []))]
            paths = [sent / name for name in names]
            for path, text in zip(paths, texts, strict=True):
                write_atomically(path, text)
            outcomes = update_workspace(
                repositories,
                self.workspace,
                options,
                lambda path, stage: self._set(job, path, stage),
                lambda outcome: self._set(job, outcome.path, outcome.result),
            )
            remember_files(self.workspace, paths[0], paths[1:])
        return [o.to_dict() for o in outcomes], all(o.ok for o in outcomes)

    def _build(self, job: dict[str, Any], args: dict[str, Any]) -> tuple[Any, bool]:
        from msctl.workspace import workspace_lock
        from msctl.workspace.build import Builder, BuildOptions
        from msctl.workspace.packages import find_packages

        if not self.workspace.is_dir():
            raise MsctlError(f"{self.workspace} does not exist yet: `msctl update --all` first")
        graph = find_packages(self.workspace)
        names = args.get("packages_up_to") or []
        keys = graph.up_to(names) if names else graph.order()
        for key in keys:
            self._set(job, graph.packages[key].name, "waiting")
        options = BuildOptions(offline=args.get("offline", False), wheelhouse=self.wheelhouse)
        with workspace_lock(self.workspace, "build"):
            result = Builder(
                graph, options, lambda name, status, _detail: self._set(job, name, status)
            ).run(keys)
        return result.to_dict(), result.ok

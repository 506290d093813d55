"""Real git and real pip for the workspace tests: bare remotes in a temporary directory,
served by ``file://`` URLs, and tiny Python packages.

Nothing here reaches the network: remotes are local bare repositories, and pip runs with
``--no-index`` against wheelhouses built here.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

_IDENTITY = ("-c", "user.name=Test Rig", "-c", "user.email=rig@example.org")


def git(*args: str, cwd: Path | None = None) -> str:
    """Run git (with an identity for commits); its stdout, stripped."""
    env = {**os.environ, "GIT_TERMINAL_PROMPT": "0", "LC_ALL": "C"}
    result = subprocess.run(
        ["git", *_IDENTITY, "-c", "init.defaultBranch=main", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if result.returncode != 0:
        raise AssertionError(f"git {' '.join(args)} failed: {result.stderr}")
    return result.stdout.strip()


class Remote:
    """A bare repository (the "server") and a scratch clone used to push to it.

    Args:
        root: A temporary directory holding both.
        name: The repository's name.
        files: The first commit's files on ``main``.
    """

    def __init__(self, root: Path, name: str, files: dict[str, str] | None = None):
        self.name = name
        self.bare = root / "remotes" / f"{name}.git"
        self.scratch = root / "scratch" / name
        self.bare.parent.mkdir(parents=True, exist_ok=True)
        git("init", "--quiet", "--bare", str(self.bare))
        git("init", "--quiet", str(self.scratch))
        git("remote", "add", "origin", str(self.bare), cwd=self.scratch)
        self.commit(files or {"README.md": f"# {name}\n"}, "first commit")
        git("push", "--quiet", "-u", "origin", "main", cwd=self.scratch)
        git("symbolic-ref", "HEAD", "refs/heads/main", cwd=self.bare)

    @property
    def url(self) -> str:
        """Its ``file://`` URL."""
        return f"file://{self.bare}"

    def commit(self, files: dict[str, str], message: str, branch: str | None = None) -> str:
        """Commit ``files`` on ``branch`` (created from the current one) without pushing."""
        if branch is not None:
            if git("branch", "--list", branch, cwd=self.scratch):
                git("checkout", "--quiet", branch, cwd=self.scratch)
            else:
                git("checkout", "--quiet", "-b", branch, cwd=self.scratch)
        for relative, text in files.items():
            path = self.scratch / relative
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
            git("add", relative, cwd=self.scratch)
        git("commit", "--quiet", "-m", message, cwd=self.scratch)
        return git("rev-parse", "HEAD", cwd=self.scratch)

    def push(self, files: dict[str, str], message: str, branch: str = "main") -> str:
        """Commit on ``branch`` and push it; returns the new commit."""
        commit = self.commit(files, message, branch)
        git("push", "--quiet", "origin", branch, cwd=self.scratch)
        return commit

    def tag(self, name: str, ref: str = "HEAD") -> str:
        """Tag ``ref`` and push the tag; returns the commit."""
        git("tag", name, ref, cwd=self.scratch)
        git("push", "--quiet", "origin", name, cwd=self.scratch)
        return git("rev-parse", f"{name}^{{commit}}", cwd=self.scratch)


def repos_text(entries: dict[str, tuple[str, str | None]]) -> str:
    """A ``.repos`` file: ``{path: (url, version)}``."""
    lines = ["repositories:"]
    for path, (url, version) in entries.items():
        lines += [f"  {path}:", "    type: git", f"    url: {url}"]
        if version is not None:
            lines.append(f"    version: {version}")
    return "\n".join(lines) + "\n"


def head(clone: Path) -> str:
    """The commit checked out in a clone."""
    return git("rev-parse", "HEAD", cwd=clone)


def branch(clone: Path) -> str:
    """The branch checked out in a clone ("" when detached)."""
    result = subprocess.run(
        ["git", "symbolic-ref", "--short", "-q", "HEAD"],
        cwd=clone,
        capture_output=True,
        text=True,
        check=False,
    )
    return result.stdout.strip()


# --------------------------------------------------------------------------- Python packages
#: A complete PEP 517 / PEP 660 build backend with no requirements of its own, so real pip
#: builds and installs the test packages with no index and nothing preinstalled: pure
#: Python wheels (``py3-none-any``) from ``[project]`` name, version and dependencies.
BACKEND = '''\
"""rig_backend: the tests' own PEP 517 build backend (pure-Python wheels)."""

import base64
import hashlib
import os
import tomllib
import zipfile


def _project():
    with open("pyproject.toml", "rb") as handle:
        return tomllib.load(handle)["project"]


def _dist(project):
    return project["name"].replace("-", "_").replace(".", "_")


def _metadata(project):
    lines = ["Metadata-Version: 2.1", f"Name: {project['name']}", f"Version: {project['version']}"]
    lines += [f"Requires-Dist: {r}" for r in project.get("dependencies", [])]
    return "\\n".join(lines) + "\\n"


def _record(name, data):
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{name},sha256={digest},{len(data)}"


def _wheel(directory, files):
    project = _project()
    dist, version = _dist(project), project["version"]
    info = f"{dist}-{version}.dist-info"
    files = dict(files)
    files[f"{info}/METADATA"] = _metadata(project).encode()
    files[f"{info}/WHEEL"] = (
        b"Wheel-Version: 1.0\\nGenerator: rig_backend\\nRoot-Is-Purelib: true\\n"
        b"Tag: py3-none-any\\n"
    )
    record = [_record(name, data) for name, data in files.items()] + [f"{info}/RECORD,,"]
    files[f"{info}/RECORD"] = ("\\n".join(record) + "\\n").encode()
    name = f"{dist}-{version}-py3-none-any.whl"
    with zipfile.ZipFile(os.path.join(directory, name), "w") as archive:
        for path, data in files.items():
            archive.writestr(path, data)
    return name


def _sources(project):
    module = project["name"].replace("-", "_")
    files = {}
    for folder, _dirs, names in os.walk(module):
        for file in sorted(names):
            if file.endswith(".py"):
                path = os.path.join(folder, file)
                with open(path, "rb") as handle:
                    files[path.replace(os.sep, "/")] = handle.read()
    return files


def get_requires_for_build_wheel(config_settings=None):
    return []


def get_requires_for_build_editable(config_settings=None):
    return []


def build_wheel(wheel_directory, config_settings=None, metadata_directory=None):
    return _wheel(wheel_directory, _sources(_project()))


def build_editable(wheel_directory, config_settings=None, metadata_directory=None):
    project = _project()
    pth = (os.path.abspath(".") + "\\n").encode()
    return _wheel(wheel_directory, {f"__editable__.{_dist(project)}.pth": pth})
'''


def python_package(
    root: Path,
    name: str,
    depends: list[str] | tuple[str, ...] = (),
    version: str = "0.1.0",
    body: str = "",
    backend: str = "in-tree",
) -> Path:
    """A tiny Python package ``root/name`` (module ``name`` with ``VALUE``).

    Args:
        root: Where to create it.
        name: The distribution name (its module: ``-`` as ``_``).
        depends: Its ``[project].dependencies``.
        version: Its version.
        body: The module's text (default: ``VALUE = "<name> <version>"``).
        backend: ``in-tree``: :data:`BACKEND` in the package (no build requirement);
            ``wheel``: ``rig-backend`` as a build requirement (from a wheelhouse).
    """
    module = name.replace("-", "_")
    folder = root / name
    (folder / module).mkdir(parents=True, exist_ok=True)
    deps = ", ".join(f'"{d}"' for d in depends)
    if backend == "in-tree":
        (folder / "_backend").mkdir(exist_ok=True)
        (folder / "_backend" / "rig_backend.py").write_text(BACKEND)
        system = 'requires = []\nbuild-backend = "rig_backend"\nbackend-path = ["_backend"]'
    else:
        system = 'requires = ["rig-backend"]\nbuild-backend = "rig_backend"'
    (folder / "pyproject.toml").write_text(
        f'[build-system]\n{system}\n\n[project]\nname = "{name}"\n'
        f'version = "{version}"\ndependencies = [{deps}]\n'
    )
    (folder / module / "__init__.py").write_text(body or f'VALUE = "{name} {version}"\n')
    return folder


def backend_package(root: Path) -> Path:
    """The ``rig-backend`` distribution itself (built by its own in-tree copy)."""
    folder = python_package(root, "rig-backend", body=BACKEND)
    return folder


def pip_env(**extra: str) -> dict[str, str]:
    """The environment of a pip (or msctl) run that must not reach any index: this
    machine's pip configuration left out, no index at all."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PIP_")}
    env.update(PIP_CONFIG_FILE=os.devnull, PIP_NO_INDEX="1", PIP_DISABLE_PIP_VERSION_CHECK="1")
    env.update(extra)
    return env


def build_wheel(package: Path, into: Path, python: str = sys.executable) -> Path:
    """Build ``package``'s wheel into ``into`` with real pip and no index."""
    into.mkdir(parents=True, exist_ok=True)
    subprocess.run(
        [python, "-m", "pip", "wheel", "--quiet", "--no-deps", "-w", str(into), str(package)],
        check=True,
        capture_output=True,
        env=pip_env(),
    )
    name = package.name.replace("-", "_")
    return next(into.glob(f"{name}-*.whl"))


def make_venv(where: Path) -> str:
    """A fresh, empty virtual environment whose ``python -m pip`` is this environment's pip;
    returns its interpreter.

    ``python -m venv`` installs pip from the bundled wheel, tens of seconds on a loaded
    machine; here pip's own package is linked into the new environment instead (a fraction
    of a second). It is still real pip, run by the new environment's interpreter, so it
    installs there; only pip's metadata is absent, so ``pip list`` there does not show pip.
    Without an importable pip here, the bundled one is installed the slow way.
    """
    try:
        import pip
    except ImportError:
        subprocess.run([sys.executable, "-m", "venv", str(where)], check=True, capture_output=True)
        return str(where / "bin" / "python")
    subprocess.run(
        [sys.executable, "-m", "venv", "--without-pip", str(where)], check=True, capture_output=True
    )
    python = str(where / "bin" / "python")
    purelib = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    Path(purelib, "pip").symlink_to(Path(pip.__file__).parent, target_is_directory=True)
    return python


def imports(python: str, module: str) -> str:
    """``module.VALUE`` as ``python`` imports it ("" if it cannot)."""
    result = subprocess.run(
        [python, "-c", f"import {module}; print({module}.VALUE)"],
        capture_output=True,
        text=True,
        check=False,
    )
    return result.stdout.strip()


# --------------------------------------------------------------------------- progress on screen
_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07")
_ROW = re.compile(r"^(\S+) [━╺╸ ]+ (.*?)\s+\d+:\d\d:\d\d\s*$")


def progress_rows(stderr: str) -> dict[str, str]:
    """What a rich progress view last showed on each row: ``{description: columns between
    the bar and the elapsed time}``.

    Run the command with ``TTY_COMPATIBLE=1`` so rich draws for a terminal although stderr
    is a pipe; a transient view draws its final state once more as it stops, so the last
    value of each row is the state it ended in.
    """
    rows: dict[str, str] = {}
    for line in _ANSI.sub("", stderr).replace("\r", "\n").splitlines():
        match = _ROW.match(line.strip())
        if match:
            rows[match.group(1)] = match.group(2).strip()
    return rows


#: The environment that makes rich draw its live views into a pipe (see progress_rows).
TERMINAL = {"TTY_COMPATIBLE": "1", "TERM": "xterm-256color", "COLUMNS": "200"}

"""The .repos model: vcstool's format, overlays, and every bad input named (no processes)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from vcs2l.commands.import_ import get_repositories

from msctl.errors import InputError, NotFoundError
from msctl.workspace.repos import (
    Repository,
    check_url,
    check_version,
    dump_repos,
    load,
    merge,
    parse_repos,
    read_repos,
)

BASE = """\
repositories:
  moonbot/limb:
    type: git
    url: https://git.example.org/moonbot/limb.git
    version: main
  moonbot/wheel:
    type: git
    url: git@git.example.org:moonbot/wheel.git
    version: v1.2
  tools/common:
    type: git
    url: file:///srv/git/common.git
"""


def test_a_workspace_file_reads_as_vcstool_writes_it() -> None:
    repos = merge(parse_repos(BASE, "ws.repos"))
    assert [(r.path, r.url, r.version) for r in repos] == [
        ("moonbot/limb", "https://git.example.org/moonbot/limb.git", "main"),
        ("moonbot/wheel", "git@git.example.org:moonbot/wheel.git", "v1.2"),
        ("tools/common", "file:///srv/git/common.git", None),
    ]
    assert repos[0].defined_at == "ws.repos:2"
    assert repos[1].version_at == "ws.repos:9"


def test_a_version_is_kept_as_written_not_as_yaml_reads_it() -> None:
    # YAML would read 1.10 as the float 1.1; a tag named 1.10 must stay 1.10.
    text = "repositories:\n  a:\n    type: git\n    url: /srv/a.git\n    version: 1.10\n"
    assert merge(parse_repos(text, "f"))[0].version == "1.10"


def test_an_overlay_changes_version_and_url_and_adds_repositories() -> None:
    overlay = """\
repositories:
  moonbot/limb:
    version: sand-field-2026
  moonbot/wheel:
    url: https://git.example.org/fork/wheel.git
  experiments/sand:
    type: git
    url: https://git.example.org/experiments/sand.git
    version: main
"""
    repos = merge(parse_repos(BASE, "ws.repos"), [parse_repos(overlay, "exp.repos", overlay=True)])
    by_path = {r.path: r for r in repos}
    assert by_path["moonbot/limb"].version == "sand-field-2026"
    assert by_path["moonbot/limb"].version_at == "exp.repos:3"
    assert by_path["moonbot/limb"].url == "https://git.example.org/moonbot/limb.git"
    assert by_path["moonbot/wheel"].url == "https://git.example.org/fork/wheel.git"
    assert by_path["moonbot/wheel"].version == "v1.2"
    assert by_path["experiments/sand"].defined_at == "exp.repos:6"
    assert list(by_path) == ["moonbot/limb", "moonbot/wheel", "tools/common", "experiments/sand"]


def test_later_overlays_win() -> None:
    first = "repositories:\n  moonbot/limb:\n    version: a\n"
    second = "repositories:\n  moonbot/limb:\n    version: b\n"
    repos = merge(
        parse_repos(BASE, "ws.repos"),
        [parse_repos(first, "1.repos", overlay=True), parse_repos(second, "2.repos", overlay=True)],
    )
    assert repos[0].version == "b" and repos[0].version_at == "2.repos:3"


def test_an_overlay_naming_an_unknown_repository_without_url_is_a_typo() -> None:
    overlay = "repositories:\n  moonbot/lmb:\n    version: x\n"
    with pytest.raises(InputError) as caught:
        merge(parse_repos(BASE, "ws.repos"), [parse_repos(overlay, "exp.repos", overlay=True)])
    text = str(caught.value)
    assert "exp.repos:2" in text and "'moonbot/lmb'" in text and "ws.repos" in text
    assert "did you mean 'moonbot/limb'" in text
    assert "type and url" in text


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            "repositories:\n  a:\n    type: git\n    url: [x\n",
            ["f.repos:4: not valid YAML (in repository 'a')"],
        ),
        (
            "repositories:\n  a:\n    type: git\n    url: /x\n"
            "  'moonbot/wheel':\n    type: git\n   url: /y\n",
            ["f.repos:7: not valid YAML (in repository 'moonbot/wheel')"],
        ),
        ("repositories:\n  a:\n    type: git\n\turl: /x\n", ["f.repos:4", "repository 'a'"]),
        ("repositories:\n  a:\n    type: gti\n    url: /x\n", ["f.repos:2", "'a'", "'gti'", "git"]),
        ("repositories:\n  a:\n    type: hg\n    url: /x\n", ["'a'", "git repositories only"]),
        ("repositories:\n  a:\n    type: git\n", ["f.repos:2", "'a'", "missing 'url'"]),
        ("repositories:\n  a:\n    url: /x\n", ["'a'", "missing 'type'"]),
        (
            "repositories:\n  a:\n    type: git\n    url: /x\n    verison: main\n",
            ["'a'", "'verison'", "line 5", "did you mean 'version'"],
        ),
        (
            "repositories:\n  a:\n    type: git\n    url: /x\n  a:\n    type: git\n    url: /y\n",
            ["'a'", "twice", "lines 2 and 5"],
        ),
        ("repositories:\n  ../escape:\n    type: git\n    url: /x\n", ["f.repos:2", "../escape"]),
        ("repositories:\n  /abs:\n    type: git\n    url: /x\n", ["'/abs'", "plain relative"]),
        (
            "repositories:\n  a:\n    type: git\n    url: /x\n  a/b:\n    type: git\n    url: /y\n",
            ["'a/b'", "inside repository 'a'"],
        ),
        ("- git: {local-name: a, uri: /x}\n", ["rosinstall"]),
        ("", ["empty"]),
        ("other: 1\n", ["no `repositories:`"]),
        (
            "repositories:\n  a:\n    type: git\n    url: /x\n    version: 'main; rm -rf /'\n",
            ["'a'", "line 5", "not a branch, tag or commit"],
        ),
    ],
)
def test_a_malformed_file_names_the_file_the_line_and_the_repository(
    text: str, expected: list[str]
) -> None:
    with pytest.raises(InputError) as caught:
        parse_repos(text, "f.repos")
    for part in expected:
        assert part in str(caught.value)


@pytest.mark.parametrize(
    "url",
    [
        "https://host/repo.git; rm -rf ~",
        "https://host/$(whoami).git",
        "https://host/`id`.git",
        "file:///srv/a.git && echo",
        "ext::sh -c touch% /tmp/pwned",
        "ext::ssh host",
        "fd::17",
        "-uhttps://host/x.git",
        "--upload-pack=touch /tmp/x",
        "ftp://host/x.git",
        "relative/path",
        "https://host/repo.git\nnext",
    ],
)
def test_urls_that_are_not_plain_git_urls_are_refused(url: str) -> None:
    with pytest.raises(InputError) as caught:
        check_url(url, "f.repos:3: repository 'a'")
    assert "f.repos:3" in str(caught.value)


@pytest.mark.parametrize(
    "url",
    [
        "https://github.com/org/repo.git",
        "ssh://git@host:2222/org/repo.git",
        "ssh://[::1]/srv/repo.git",
        "git@github.com:org/repo.git",
        "file:///tmp/x/remotes/a.git",
        "/srv/git/a.git",
    ],
)
def test_plain_git_urls_pass(url: str) -> None:
    assert check_url(url, "here") == url


@pytest.mark.parametrize("version", ["main", "feature/x-2", "v1.2.3", "1a2b3c4", "release+1"])
def test_plain_versions_pass(version: str) -> None:
    assert check_version(version, "here") == version


@pytest.mark.parametrize("version", ["-b", "a..b", "a b", "x@{1}", "a.lock", "a/", "~1", ""])
def test_odd_versions_are_refused(version: str) -> None:
    with pytest.raises(InputError):
        check_version(version, "here")


def test_a_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(NotFoundError) as caught:
        read_repos(tmp_path / "nope.repos")
    assert "nope.repos" in str(caught.value)


def test_what_msctl_writes_vcs2l_reads_the_same(tmp_path: Path) -> None:
    repos = [
        Repository("src/a", "https://host/a.git", "0123456789abcdef0123456789abcdef01234567"),
        Repository("src/b", "file:///srv/b.git", "main"),
        Repository("c", "/srv/c.git", None),
    ]
    path = tmp_path / "lock.repos"
    path.write_text(dump_repos(repos, "a header\nof two lines"))
    ours = load(path)
    assert [(r.path, r.url, r.version) for r in ours] == [(r.path, r.url, r.version) for r in repos]
    with path.open() as handle:
        theirs = get_repositories(handle)
    assert theirs == {
        "src/a": {"type": "git", "url": "https://host/a.git", "version": repos[0].version},
        "src/b": {"type": "git", "url": "file:///srv/b.git", "version": "main"},
        "c": {"type": "git", "url": "/srv/c.git"},
    }


def test_a_vcstool_file_with_comments_and_flow_style_reads(tmp_path: Path) -> None:
    text = (
        "# the field's workspace\n"
        "repositories:\n"
        "  a: {type: git, url: 'https://host/a.git', version: main}  # inline\n"
    )
    repos = merge(parse_repos(text, "f"))
    assert repos == [
        Repository("a", "https://host/a.git", "main", defined_at="f:3", version_at="f:3")
    ]
    assert yaml.safe_load(dump_repos(repos))["repositories"]["a"]["version"] == "main"

"""The template's ``[safety] operator_timeout``: its default, its checks, and the lock."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from msctl.assembler import resolve
from msctl.assembler.data import OPERATOR_TIMEOUT, load_template
from msctl.errors import InputError

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def assemblies(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A private copy of the shipped templates and module types."""
    copy = tmp_path / "assemblies"
    shutil.copytree(REPO / "assemblies", copy, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setenv("MSCTL_ASSEMBLIES_DIR", str(copy))
    return copy


def with_safety(assemblies: Path, template: str, table: str) -> None:
    path = assemblies / f"{template}.toml"
    path.write_text(path.read_text() + f"\n[safety]\n{table}\n")


def test_on_by_default_with_stations_off_without(assemblies: Path) -> None:
    assert load_template("dragon").operator_timeout == OPERATOR_TIMEOUT == 3.0
    assert load_template("minimal").operator_timeout is None  # no station: nobody to lose
    lock = resolve("dragon").lock
    assert lock.operator_timeout == 3.0


def test_a_template_sets_it_or_turns_it_off(assemblies: Path) -> None:
    with_safety(assemblies, "dragon", "operator_timeout = 5")
    with_safety(assemblies, "tricycle", "operator_timeout = false")
    with_safety(assemblies, "minimal", "operator_timeout = 1.5")
    assert load_template("dragon").operator_timeout == 5.0
    assert load_template("tricycle").operator_timeout is None
    # Asked for with no station: only a claim holder attends its modules.
    assert load_template("minimal").operator_timeout == 1.5
    assert resolve("dragon").lock.operator_timeout == 5.0


@pytest.mark.parametrize(
    ("table", "said"),
    [
        ("operator_timeout = 0", "field safety.operator_timeout is 0"),
        ("operator_timeout = -2.0", "field safety.operator_timeout is -2.0"),
        ("operator_timeout = true", "field safety.operator_timeout is True"),
        ('operator_timeout = "3 s"', "field safety.operator_timeout is '3 s'"),
        ("operator_timout = 3.0", "field safety.operator_timout is not a template safety"),
    ],
)
def test_a_bad_value_names_the_file_and_field(assemblies: Path, table: str, said: str) -> None:
    with_safety(assemblies, "dragon", table)
    with pytest.raises(InputError) as caught:
        load_template("dragon")
    text = str(caught.value)
    assert str(assemblies / "dragon.toml") in text and said in text, text

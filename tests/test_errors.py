"""One error root: the runtime's categories, their builtins, and their exit codes."""

from __future__ import annotations

import pytest

from components.errors import (
    ComponentError,
    ConfigError,
    DeadlineError,
    HardwareError,
    LinkError,
    NotFound,
)
from msctl.errors import (
    InputError,
    MsctlError,
    NetworkError,
    NotFoundError,
    OperationTimeout,
    exit_code_of,
)


@pytest.mark.parametrize(
    ("category", "builtin", "code"),
    [
        (ConfigError, ValueError, 2),
        (LinkError, ConnectionError, 3),
        (NotFound, LookupError, 4),
        (DeadlineError, TimeoutError, 5),
        (HardwareError, OSError, 6),
    ],
)
def test_each_category_is_its_builtin_and_has_one_exit_code(
    category: type[ComponentError], builtin: type[BaseException], code: int
) -> None:
    error = category("joint3: no answer")
    assert isinstance(error, ComponentError) and isinstance(error, builtin)
    assert str(error) == "joint3: no answer"
    assert exit_code_of(error) == code


def test_msctl_errors_share_the_root_and_keep_their_codes() -> None:
    assert exit_code_of(ComponentError("plain")) == 1
    for error, code in [
        (MsctlError("x"), 1),
        (InputError("x"), 2),
        (NetworkError("x"), 3),
        (NotFoundError("x"), 4),
        (OperationTimeout("x"), 5),
        (MsctlError("x", exit_code=3), 3),
        (InputError("x", exit_code=7), 7),
    ]:
        assert isinstance(error, ComponentError)
        assert error.exit_code == code == exit_code_of(error)


def test_a_class_with_its_own_code_keeps_it() -> None:
    class Unwritable(MsctlError, OSError):
        exit_code = 3

    assert exit_code_of(Unwritable("home")) == 3
    assert exit_code_of(Unwritable("home", exit_code=8)) == 8


def test_a_hint_follows_the_message() -> None:
    assert str(ConfigError("bad rate", hint="give a number")) == "bad rate — give a number"
    assert str(InputError("bad rate", hint="give a number")) == "bad rate — give a number"


def test_runtime_errors_are_rooted_on_component_error() -> None:
    from components.comm.session import SessionConfigError

    assert issubclass(SessionConfigError, ConfigError)
    assert exit_code_of(SessionConfigError("MSCTL_ZENOH_CONNECT: bad endpoint")) == 2

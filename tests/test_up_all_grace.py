"""How long `msctl up --all` keeps asking a host its graph does not show, per link class.

A host off the graph may be one whose radio link is being opened again (noticed dead after its
lease, then a handshake of a few round trips): it is asked for two leases of the slower of its
link and this computer's before it is named unreachable, never less than 3 s nor more than the
whole start's timeout.
"""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from components.links import DEFAULTS, Network
from msctl.launcher.remote import UP_GRACE, UP_GRACE_LEASES, _graces


def assembly(links: dict[str, str]) -> SimpleNamespace:
    return SimpleNamespace(network=Network(dict(DEFAULTS), links).as_dict())


def test_a_radio_host_gets_two_radio_leases(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MSCTL_HOST", "ground1")
    graces = _graces(assembly({}), ["hl-limb-01"], timeout=120)
    assert graces == {"hl-limb-01": UP_GRACE_LEASES * DEFAULTS["radio"].lease_s}


def test_the_slower_end_sets_it_and_the_timeout_bounds_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("MSCTL_HOST", "ground1")
    links = {"hl-limb-01": "wired", "ground1": "wired", "hl-wheel-02": "deep-space"}
    graces = _graces(assembly(links), ["hl-limb-01", "hl-wheel-02"], timeout=45)
    # Both ends wired: two 2 s leases is 4 s, above the 3 s floor.
    assert graces["hl-limb-01"] == max(UP_GRACE, UP_GRACE_LEASES * DEFAULTS["wired"].lease_s)
    # A deep-space link's 30 s lease twice is past the start's own 45 s: the timeout bounds it.
    assert graces["hl-wheel-02"] == 45


def test_a_lock_without_link_classes_is_the_defaults(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MSCTL_HOST", "ground1")
    graces = _graces(SimpleNamespace(network={}), ["a", "b"], timeout=2)
    assert graces == {"a": 2, "b": 2}

"""A robot stops its own motors when it loses its operators, on a rehearsal of ``dragon``.

``msctl rehearse up dragon --link wifi --detach`` stands up the four robot computers and
ground1 (the ground station, station ``gc1``) and runs ``msctl up --all`` from it. Cutting
ground1's radio link leaves every robot computer with no visible operator: after the
template's ``operator_timeout`` (3 s, dragon's default) each module's joint manager holds its
motors and says why, which each robot computer's own ``msctl health`` shows (the ground
cannot hear them then). When the link returns, the hold lifts by itself and the ground sees
every module OK again.

Needs root (CI runs as root); skipped, saying so, without it.
"""

from __future__ import annotations

import json
import re
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest
from conftest import wait_until
from rehearse_rigs import GROUND, ROBOTS, ROOT_REHEARSAL, Stage

pytestmark = [
    pytest.mark.e2e,
    pytest.mark.timeout(900),
    ROOT_REHEARSAL,
]

#: What every module's joint manager says on each joint while it holds (dragon: station gc1).
HELD = "held: no operator: gc1 (ground1) unreachable"
#: Seconds past the 3 s threshold a hold may take to show: the lease (about 1 s), a health
#: publication, and five computers sharing a loaded machine's two cores with the suite.
BOUND = 120.0


@pytest.fixture(scope="module")
def stage(dragon: Stage) -> Stage:
    """The suite's shared rehearsal of dragon (conftest.DRAGON_REHEARSAL)."""
    return dragon


def health(stage: Stage, host: str) -> dict[str, Any]:
    """``msctl health --once --json`` on computer ``host``."""
    done = stage.on(host, "health", "--once", "--json", "--timeout", "15")
    assert done.returncode in (0, 1), done.stderr
    return json.loads(done.stdout)


def row(document: dict[str, Any], module: str) -> dict[str, Any] | None:
    return next((r for r in document["modules"] if r["name"] == module), None)


def all_ok(document: dict[str, Any]) -> bool:
    """Every item of every module OK (a rate may WARN on a loaded machine), but the computers'
    own CPU and memory, which are this shared machine's."""
    return all(
        item["level"] == "OK" or (item["level"] == "WARN" and "/topics/" in item["name"])
        for r in document["modules"]
        for item in r["items"]
        if "/host/" not in item["name"]
    )


def held_items(document: dict[str, Any], module: str) -> list[dict[str, Any]]:
    """The module's items that report the presence hold."""
    found = row(document, module)
    return [
        item
        for item in (found or {}).get("items", [])
        if item["level"] == "ERROR" and HELD in item["message"]
    ]


def all_motors_held(document: dict[str, Any], module: str) -> list[dict[str, Any]]:
    """The module's motor items once every one of them reports the hold (else [])."""
    found = row(document, module) or {"items": []}
    motors = {
        i["name"]
        for i in found["items"]
        if f"{module}/motors/" in i["name"] and not i["name"].endswith("/bus")
    }
    held = held_items(document, module)
    return held if motors and {i["name"] for i in held} == motors else []


def test_cut_from_the_ground_every_module_holds_itself_then_is_ok_again(stage: Stage) -> None:
    wait_until(
        lambda: all_ok(health(stage, GROUND)), timeout=BOUND * 2, what="every module OK first"
    )
    assert not any(held_items(health(stage, host), m) for m, host in ROBOTS.items())

    done = stage.msctl("rehearse", "link", GROUND, "--down", "0")
    assert done.returncode == 0, done.stderr
    cut = time.monotonic()
    try:

        def held_on_its_computer(module: str) -> tuple[float, list[dict[str, Any]]]:
            last: dict[str, Any] = {"modules": []}

            def held() -> list[dict[str, Any]]:
                # Read on the robot computer itself: the ground cannot hear it now.
                last.update(health(stage, ROBOTS[module]))
                return all_motors_held(last, module)

            items = wait_until(
                held,
                timeout=3.0 + BOUND,
                what=lambda: (
                    f"{module}'s presence hold in its own health on "
                    f"{ROBOTS[module]}; its last row there: {row(last, module)}"
                ),
            )
            return time.monotonic() - cut, items

        with ThreadPoolExecutor(len(ROBOTS)) as pool:
            seen = dict(zip(ROBOTS, pool.map(held_on_its_computer, ROBOTS), strict=True))
        for module, (after, items) in seen.items():
            # A figure, not a bound: when the last operator vanished, from what it says.
            alone = float(re.search(r"unreachable for ([0-9.]+) s", items[0]["message"])[1])
            print(
                f"{module}: every motor ({len(items)}) held in its own health, read "
                f"{after:.1f} s after the cut; gc1 gone from its router about "
                f"{after - alone:.1f} s after the cut: {items[0]['message']}"
            )
    finally:
        done = stage.msctl("rehearse", "link", GROUND, "--up")
        assert done.returncode == 0, done.stderr
    back = time.monotonic()

    def lifted_on_its_computer(module: str) -> float:
        # The hold lifts by itself once gc1's tokens are back on the robot's router.
        wait_until(
            lambda: not held_items(health(stage, ROBOTS[module]), module),
            timeout=BOUND,
            what=f"{module}'s presence hold lifted on {ROBOTS[module]}",
        )
        return time.monotonic() - back

    with ThreadPoolExecutor(len(ROBOTS)) as pool:
        lifted = dict(zip(ROBOTS, pool.map(lifted_on_its_computer, ROBOTS), strict=True))
    print("hold lifted, read on each computer, s after the return:", lifted)
    latest: list[dict[str, Any]] = []

    def ok_at_the_ground() -> dict[str, Any] | None:
        latest[:] = [health(stage, GROUND)]
        return latest[0] if all_ok(latest[0]) else None

    try:
        document = wait_until(ok_at_the_ground, timeout=BOUND, what="every module OK at the ground")
    except AssertionError as exc:
        raise AssertionError(f"{exc}; not OK: {not_ok(latest[0]) if latest else '?'}") from None
    print(f"every module OK at the ground {time.monotonic() - back:.1f} s after the link returned")
    assert {r["name"] for r in document["modules"]} == set(ROBOTS)
    assert not any(held_items(document, module) for module in ROBOTS)


def not_ok(document: dict[str, Any]) -> list[str]:
    """What keeps a health document from :func:`all_ok`, for a failure's message."""
    return [
        f"{item['name']} {item['level']}: {item['message']}"
        for r in document["modules"]
        for item in r["items"]
        if "/host/" not in item["name"]
        and not (item["level"] == "OK" or (item["level"] == "WARN" and "/topics/" in item["name"]))
    ]

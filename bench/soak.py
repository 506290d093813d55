"""Soak benchmark: a whole assembly on the rehearsal, over radio links, for minutes on end.

Run ``sudo python bench/soak.py [--template two_dragons] [--link field-wifi] [--minutes 10]
[--estop-every 30] [--json]`` (root, or unprivileged user namespaces, as ``msctl rehearse``).
The paper's field experiment (two Dragons, eight robot computers, their ground stations and
operators, 60 components, over field Wi-Fi) as issue 31 asks it: in a temporary
``MSCTL_HOME``, ``msctl rehearse up TEMPLATE --link LINK --detach`` (secure: mutual TLS,
access control; ``up --all`` from the ground station), then for ``--minutes``:

- every ``--estop-every`` seconds an ``msctl estop --json`` on the ground station, then
  ``msctl recover --json``: each module's acknowledgement, and every module that did not
  acknowledge (a lost halt) named;
- every minute ``msctl health --once --json`` on the ground station: how many modules are OK;
- the machine's load average and the rehearsal's CPU (its processes' user+system seconds
  from ``/proc``), so that where the two shared cores, not the links, are the limit, the figure
  says so.

At the end: ``msctl ps --all --json`` (every component's restarts since the start: a
component restarted is a failure of the soak), ``msctl health --once --json`` (every module
OK), each link's bytes per second both ways over the soak (the link emulator's counters).
``msctl rehearse down`` always, also after an error or Ctrl-C.

There is no bare baseline for "stable for ten minutes": the figures are absolute; the e-stop
acknowledgements are put beside ``bench/rehearse.py``'s bare round trips on the same profile.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # runnable as `python bench/soak.py` from anywhere
    sys.path.insert(0, str(ROOT))

from bench.rehearse import (  # noqa: E402
    Stage,
    health_all_ok,
    link_rates,
    log,
    no_ack_messages,
    parse_estop,
    tail_percentile,
)

#: Seconds ``rehearse up`` (agents, then ``up --all`` of 60 components) may take.
UP_WITHIN = 900.0
#: Seconds one command on the ground station may take.
COMMAND_WITHIN = 120.0
#: Seconds each module has to acknowledge a halt (``msctl estop --timeout``).
ESTOP_TIMEOUT = 5.0


class Soak(Stage):
    """A rehearsal of ``template`` (:class:`bench.rehearse.Stage` for another template)."""

    def __init__(self, home: Path, profile: str, template: str) -> None:
        super().__init__(home, profile)
        self.template = template

    def up_whole(self) -> float:
        """``msctl rehearse up TEMPLATE --link PROFILE --detach``: seconds it took.

        Raises:
            RuntimeError: If it did not come up (its last line said why).
        """
        from msctl.rehearse.rehearsal import Rehearsal

        started = time.monotonic()
        done = self.msctl(
            "rehearse", "up", self.template, "--link", self.profile, "--detach",
            "--timeout", f"{UP_WITHIN - 60:g}",
            timeout=UP_WITHIN,
        )  # fmt: skip
        if done is None:
            raise RuntimeError(f"msctl rehearse up: not within {UP_WITHIN:g} s")
        if done.returncode != 0:
            last = (done.stderr or done.stdout).strip().splitlines()[-3:]
            raise RuntimeError(f"msctl rehearse up failed ({done.returncode}): {last}")
        self.rehearsal = Rehearsal.load(self.home / "rehearse")
        return time.monotonic() - started

    def ground_json(self, *args: str) -> tuple[int | None, Any]:
        """``msctl ARGS`` on the ground station: its exit code (``None``: timed out) and its
        JSON document (``None``: none)."""
        done, _ = self.msctl_on(self.ground, *args, timeout=COMMAND_WITHIN)
        if done is None:
            return None, None
        try:
            return done.returncode, json.loads(done.stdout)
        except ValueError:
            return done.returncode, None

    def rehearsal_cpu_s(self) -> float:
        """User+system CPU seconds so far of every process in the rehearsal's namespaces."""
        total = 0.0
        ticks = os.sysconf("SC_CLK_TCK")
        names = set()
        for computer in self.rehearsal.computers:  # root mode: /run/netns/NAME
            with contextlib.suppress(OSError):
                names.add(f"net:[{os.stat(f'/run/netns/{computer.netns}').st_ino}]")
        for pid in filter(str.isdigit, os.listdir("/proc")):
            try:
                if os.readlink(f"/proc/{pid}/ns/net") not in names:
                    continue
                fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            total += (int(fields[11]) + int(fields[12])) / ticks
        return total


def restarts(document: Any) -> dict[str, tuple[Any, int]]:
    """Component -> ``(pid, restarts)`` of an ``msctl ps --all --json`` document."""
    rows = (document or {}).get("components") or []
    return {
        f"{r.get('host')}:{r['name']}": (r.get("pid"), int(r.get("restarts") or 0)) for r in rows
    }


def restarted(before: dict[str, tuple[Any, int]], after: dict[str, tuple[Any, int]]) -> list[str]:
    """Components whose process changed or whose restarts grew between two :func:`restarts`,
    and those that vanished."""
    changed = [
        name
        for name, (pid, count) in after.items()
        if name in before and (before[name][0] != pid or before[name][1] != count)
    ]
    return sorted(changed + [f"{name} (gone)" for name in before if name not in after])


def modules_ok(document: Any) -> tuple[int, int]:
    """``(OK, all)`` modules of an ``msctl health --once --json`` document (as
    :func:`bench.rehearse.health_all_ok` judges a module: the computers' own CPU and memory
    items aside)."""
    rows = (document or {}).get("modules") or []
    ok = sum(health_all_ok({"modules": [row]}) for row in rows)
    return ok, len(rows)


def soak(stage: Soak, minutes: float, estop_every: float) -> dict[str, Any]:
    """Stand the rehearsal up, run the soak, and return its figures (the rehearsal stays)."""
    result: dict[str, Any] = {"template": stage.template, "link": stage.profile}
    log(f"soak: msctl rehearse up {stage.template} --link {stage.profile} ...")
    result["up_s"] = round(stage.up_whole(), 1)
    log(f"soak: up in {result['up_s']} s; {minutes:g} min of it")
    code, ps_before = stage.ground_json("ps", "--all", "--json")
    before = restarts(ps_before)
    result["components"] = len(before)
    result["ps_before_exit"] = code
    links_before = stage.link({"op": "status"})
    cpu_before, started = stage.rehearsal_cpu_s(), time.monotonic()
    acks: list[float | None] = []
    lost: list[str] = []
    health: list[dict[str, Any]] = []
    loads: list[float] = []
    rounds = 0
    next_health = started
    end = started + minutes * 60.0
    while time.monotonic() < end:
        rounds += 1
        done, _ = stage.msctl_on(stage.ground, "estop", "--json", "--timeout", f"{ESTOP_TIMEOUT:g}")
        stdout = done.stdout if done is not None else ""
        found = parse_estop(stdout)
        acks += list(found.values())
        lost += [f"round {rounds}: {m}" for m in no_ack_messages(stdout)]
        if done is None:
            lost.append(f"round {rounds}: msctl estop did not end within {COMMAND_WITHIN:g} s")
        stage.msctl_on(stage.ground, "recover", "--json", "--timeout", f"{ESTOP_TIMEOUT:g}")
        loads.append(os.getloadavg()[0])
        if time.monotonic() >= next_health:
            _, document = stage.ground_json("health", "--once", "--json")
            ok, every = modules_ok(document)
            health.append({"at_s": round(time.monotonic() - started), "ok": ok, "of": every})
            log(f"soak: {time.monotonic() - started:5.0f} s  modules OK {ok}/{every}  "
                f"halts acknowledged {sum(a is not None for a in acks)}/{len(acks)}  "
                f"load {loads[-1]:.1f}")  # fmt: skip
            next_health += 60.0
        pause = started + rounds * estop_every - time.monotonic()
        if pause > 0:
            time.sleep(min(pause, max(end - time.monotonic(), 0)))
    seconds = time.monotonic() - started
    cpu = stage.rehearsal_cpu_s() - cpu_before
    rates = link_rates(links_before, stage.link({"op": "status"}))
    code, ps_after = stage.ground_json("ps", "--all", "--json")
    _, final = stage.ground_json("health", "--once", "--json")
    ok, every = modules_ok(final)
    answered = [a for a in acks if a is not None]
    result.update(
        seconds=round(seconds),
        estops=rounds,
        halts=len(acks),
        halts_acknowledged=len(answered),
        lost_halts=lost,
        ack_p50_ms=_ms(tail_percentile(acks, 50)),
        ack_p99_ms=_ms(tail_percentile(acks, 99)),
        ack_max_ms=_ms(max(answered) if answered else None),
        restarted=restarted(before, restarts(ps_after)),
        ps_after_exit=code,
        unreachable_at_end=[u.get("host") for u in (ps_after or {}).get("unreachable") or []],
        modules_ok_at_end=ok,
        modules=every,
        health=health,
        load_avg_max=round(max(loads, default=0.0), 1),
        rehearsal_cpu_cores=round(cpu / seconds, 2) if seconds else None,
        cores=os.cpu_count(),
        link_kB_s={h: {k: round(v / 1000, 1) for k, v in r.items()} for h, r in rates.items()},
    )
    return result


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else round(seconds * 1000, 1)


def print_report(result: dict[str, Any]) -> None:
    """The soak's figures as lines a person reads."""
    print(f"soak of {result['template']} over {result['link']} links")
    print(f"  rehearse up (agents, then up --all):   {result['up_s']} s")
    print(f"  components at the start:              {result['components']}")
    print(f"  soak:                                  {result['seconds']} s, "
          f"{result['estops']} e-stops")  # fmt: skip
    print(f"  halts acknowledged:                    {result['halts_acknowledged']} "
          f"of {result['halts']}")  # fmt: skip
    print(f"  ack p50 / p99 / max:                   {result['ack_p50_ms']} / "
          f"{result['ack_p99_ms']} / {result['ack_max_ms']} ms")  # fmt: skip
    print(f"  components restarted:                  {len(result['restarted'])}")
    print(f"  modules OK at the end:                 {result['modules_ok_at_end']} "
          f"of {result['modules']}")  # fmt: skip
    print(f"  hosts not answering ps at the end:     {result['unreachable_at_end'] or 'none'}")
    print(f"  the rehearsal's CPU:                   {result['rehearsal_cpu_cores']} of "
          f"{result['cores']} cores (load average up to {result['load_avg_max']})")  # fmt: skip
    for host, rate in sorted(result["link_kB_s"].items()):
        print(f"  link {host:<14} up {rate['up']:7.1f} kB/s   down {rate['down']:7.1f} kB/s")
    for line in result["lost_halts"]:
        print(f"  not acknowledged: {line}")
    for name in result["restarted"]:
        print(f"  restarted: {name}")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the soak; exit 0 when it was stable (no lost halt, no restart, every module OK)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--template", default="two_dragons")
    parser.add_argument("--link", default="field-wifi", help="every radio link's profile")
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--estop-every", type=float, default=30.0, help="seconds")
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    args = parser.parse_args(argv)
    from msctl.rehearse.computers import privileges_problem

    problem = privileges_problem()
    if problem is not None:
        print(f"bench/soak.py: {problem}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(130))
    with tempfile.TemporaryDirectory(prefix="msctl_bench_soak_") as home:
        stage = Soak(Path(home), args.link, args.template)
        try:
            result = soak(stage, args.minutes, args.estop_every)
        finally:
            if stage.rehearsal is not None or (Path(home) / "rehearse").exists():
                trouble = stage.down()
                if trouble:
                    log(f"soak: {trouble}")
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print_report(result)
    stable = (
        not result["lost_halts"]
        and not result["restarted"]
        and result["modules_ok_at_end"] == result["modules"]
    )
    return 0 if stable else 1


if __name__ == "__main__":
    sys.exit(main())

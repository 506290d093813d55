"""bench/rehearse.py's pure parts: what it reads from msctl's and the system's output, and how
it turns samples into the figures of its table (no rehearsal, no root: the benchmark itself
runs as ``sudo python bench/rehearse.py``)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _bench() -> Any:
    spec = importlib.util.spec_from_file_location("bench_rehearse", ROOT / "bench" / "rehearse.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("bench_rehearse", module)
    spec.loader.exec_module(module)
    return module


bench = _bench()


def test_estop_json_gives_each_module_its_ack_and_none_for_no_ack() -> None:
    document = {
        "verb": "halt",
        "modules": [
            {"module": "limb1", "ok": True, "message": "halted", "seconds": 0.0202},
            {"module": "wheel2", "ok": False, "message": "no answer", "seconds": None},
            {"module": "limb2", "ok": True, "message": "halted", "seconds": 0.0},
        ],
        "seconds": 0.03,
        "acknowledged": False,
        "notes": [],
    }
    assert bench.parse_estop(json.dumps(document, indent=2)) == {
        "limb1": 0.0202,
        "wheel2": None,
        "limb2": 0.0,
    }


def test_estop_lines_are_read_when_there_is_no_json() -> None:
    text = (
        "limb1   halted    20.2 ms  halted: 9 joints held\n"
        "wheel1  NO ACK          -  no answer within 2 s\n"
        "4 module(s) in 24.5 ms\n"
    )
    assert bench.parse_estop(text) == {"limb1": pytest.approx(0.0202), "wheel1": None}
    assert bench.parse_estop("") == {}


def test_a_missing_ack_is_the_slowest_sample() -> None:
    values = [0.010, 0.012, None, 0.011, 0.013]
    assert bench.tail_percentile(values, 50) == 0.012
    assert bench.tail_percentile(values, 99) is None  # the tail is the one that never came
    assert bench.tail_percentile([None, None, 0.01], 50) is None
    assert bench.tail_percentile([], 50) is None


def test_ss_counters_are_payload_plus_headers_per_segment() -> None:
    text = (
        "0      0      10.77.0.11:17447 10.77.0.201:53210\n"
        "\t cubic wscale:7,7 rto:204 bytes_sent:1000 bytes_acked:1001 bytes_received:400 "
        "segs_out:10 segs_in:8 data_segs_out:5 data_segs_in:4 send 1bps\n"
        "0      0      10.77.0.11:17447 10.77.0.201:53212\n"
        "\t cubic bytes_sent:10 bytes_received:0 segs_out:1 segs_in:1\n"
    )
    header = bench.HEADER_BYTES
    assert bench.socket_counters(text) == {
        "10.77.0.11:17447 10.77.0.201:53210": (1000 + 10 * header, 400 + 8 * header),
        "10.77.0.11:17447 10.77.0.201:53212": (10 + header, header),
    }
    assert bench.socket_counters("") == {}


def test_bytes_between_readings_survive_a_session_opened_again() -> None:
    readings = [
        {"a": (1000, 500)},
        {"a": (1100, 560)},  # then closed: its last 100/60 are kept
        {"b": (300, 200)},  # its successor: all of it is in the window
        {"b": (400, 250)},
    ]
    assert bench.bytes_between(readings) == (100 + 400, 60 + 250)
    assert bench.bytes_between([]) == (0, 0)
    assert bench.bytes_between([{"a": (5, 5)}]) == (0, 0)


def test_no_ack_messages_name_the_module() -> None:
    document = {
        "modules": [
            {
                "module": "limb1",
                "ok": False,
                "message": "no server of /limb1/halt",
                "seconds": None,
            },
            {"module": "limb2", "ok": True, "message": "halted", "seconds": 0.01},
        ]
    }
    assert bench.no_ack_messages(json.dumps(document)) == ["limb1: no server of /limb1/halt"]
    assert bench.no_ack_messages("limb1  halted  20.2 ms") == []


def test_link_rates_per_host_and_direction_over_the_emulators_clock() -> None:
    def reading(uptime: float, up: int, down: int) -> dict[str, Any]:
        host = {"up": {"bytes": up}, "down": {"bytes": down}}
        return {"uptime_s": uptime, "hosts": {"ground1": host}}

    rates = bench.link_rates(reading(100.0, 1000, 5000), reading(110.0, 3000, 25000))
    assert rates == {"ground1": {"up": 200.0, "down": 2000.0}}
    with pytest.raises(ValueError):
        bench.link_rates(reading(100.0, 0, 0), reading(100.0, 0, 0))


def test_health_all_ok_leaves_the_computers_load_and_topic_rates_aside() -> None:
    def document(*items: tuple[str, str]) -> dict[str, Any]:
        return {"modules": [{"items": [{"name": n, "level": lv} for n, lv in items]}]}

    assert bench.health_all_ok(document(("limb1/health", "OK"), ("limb1/host/cpu", "ERROR")))
    assert bench.health_all_ok(document(("limb1/topics/joint_states", "WARN")))
    assert not bench.health_all_ok(document(("limb1/health", "STALE")))
    assert not bench.health_all_ok(document(("limb1/components/joint_manager", "WARN")))
    assert not bench.health_all_ok({"modules": []})


def _alarm(at: float, item: str, to: str, module: str = "limb1") -> dict[str, Any]:
    return {"_at": at, "module": module, "item": item, "to": to}


def test_health_left_ok_during_the_outage_and_came_back_after_it() -> None:
    alarms = [
        _alarm(5.0, "limb1/host/cpu", "ERROR"),  # the computer's load: aside
        _alarm(5.0, "limb1", "ERROR"),  # the aggregate follows the cpu: aside
        _alarm(11.1, "limb1/components/joint_manager", "STALE"),
        _alarm(12.6, "limb1/health", "STALE"),
        _alarm(12.6, "limb2/health", "STALE", module="limb2"),  # another module
        _alarm(16.0, "limb1/components/joint_manager", "OK"),
        _alarm(16.4, "limb1/topics/joint_states", "WARN"),  # a rate may WARN
        _alarm(16.5, "limb1/health", "OK"),
    ]
    left, again, before = bench.health_changes(alarms, "limb1", cut=10.0, back=15.0)
    assert left == pytest.approx(1.1)
    assert again == pytest.approx(1.5)
    assert before == []


def test_health_that_never_left_ok_or_was_not_ok_already() -> None:
    assert bench.health_changes([], "limb1", cut=10.0, back=15.0) == (None, None, [])
    alarms = [
        _alarm(1.0, "limb1/motors/joint3", "ERROR"),  # before the cut: not the outage's
        _alarm(12.0, "limb1/health", "STALE"),
    ]
    left, again, before = bench.health_changes(alarms, "limb1", cut=10.0, back=15.0)
    assert (left, again, before) == (pytest.approx(2.0), None, ["limb1/motors/joint3"])


def test_first_event_after_a_moment_by_its_own_clock() -> None:
    events = [
        {"ev": "data", "t": 1.0, "source": "hl-limb-01"},
        {"ev": "data", "t": 7.5, "source": "hl-limb-02"},
        {"ev": "data", "t": 8.0, "source": "hl-limb-01"},
        {"ev": "ping", "t": 9.0},
    ]
    assert bench.first_after(events, 5.0, ev="data") == 7.5
    assert bench.first_after(events, 5.0, ev="data", source="hl-limb-01") == 8.0
    assert bench.first_after(events, 9.5, ev="data") is None
    assert bench.first_after([{"_at": 3.0, "to": "OK"}], 2.0, to="OK") == 3.0


def test_figures_that_did_not_happen_say_so() -> None:
    assert bench.fmt_s(None, 60) == "not within 60 s"
    assert bench.fmt_s(1.234, 60) == "1.23 s"
    assert bench.fmt_ms(0.0123, 5) == "12.3 ms"
    assert bench.fmt_ms(None, 5) == "not within 5 s"
    assert bench.fmt_rate(950) == "950 B/s"
    assert bench.fmt_rate(3400) == "3.4 kB/s"
    assert bench.ratio(2.0, 0.5) == "4.00x"
    assert bench.ratio(None, 0.5) == bench.ratio(2.0, None) == bench.ratio(2.0, 0.0) == "-"


def test_the_hosts_up_all_could_not_start_are_read_from_its_table() -> None:
    stderr = (
        "dragon: every host\n"
        "┏━━━━━━━━━━━━━┳━━━━━━━━━━━━┳━━━━━━━━━┳━━━━━━┓\n"
        "┃ host        ┃ components ┃ healthy ┃ note ┃\n"
        "│ hl-limb-01  │ 6          │ 6       │      │\n"
        "│ hl-limb-02  │ -          │ -       │ unreachable: no answer in 10 s │\n"
        "error: no agent answered for hl-limb-02 (started: hl-limb-01)\n"
    )
    assert bench.unreachable_rows(stderr) == ["hl-limb-02: unreachable: no answer in 10 s"]
    assert bench.unreachable_rows("") == []


def test_ps_all_shows_every_host_running_or_not() -> None:
    def ps(*rows: tuple[str, str]) -> dict[str, Any]:
        return {"components": [{"host": h, "state": st, "name": "x"} for h, st in rows]}

    hosts = {"hl-limb-01", "ground1"}
    assert bench.every_host_running(ps(("hl-limb-01", "running"), ("ground1", "running")), hosts)
    assert not bench.every_host_running(ps(("hl-limb-01", "running")), hosts)  # unreachable
    assert not bench.every_host_running(
        ps(("hl-limb-01", "running"), ("ground1", "starting")), hosts
    )


def test_link_drops_are_summed_over_links_and_directions() -> None:
    def side(packets: int, loss: int, outage: int) -> dict[str, Any]:
        return {"packets": packets, "dropped": {"loss": loss, "outage": outage, "queue": 0}}

    status = {
        "hosts": {
            "ground1": {"up": side(100, 5, 1), "down": side(200, 2, 0)},
            "hl-limb-01": {"up": side(50, 0, 3), "down": side(60, 1, 0)},
        }
    }
    run = bench.ProfileRun("field-wifi", rounds=1)
    bench.drops(run, status)
    assert run.link_packets == 410
    assert run.link_drops == {"loss": 8, "outage": 4, "queue": 0}


def test_a_profile_whose_up_failed_still_makes_a_table_and_a_document() -> None:
    run = bench.ProfileRun("wifi", rounds=3, up_all_tries=2)
    run.up_all_failures = ["exit 3 after 8.0 s: no agent answered", "not within 240 s"]
    rows = bench.profile_rows(run)
    assert rows[0][0] == "up --all -> healthy"
    assert rows[0][1] == "failed (try 1: exit 3 after 8.0 s; try 2: not within 240 s)"
    assert all(len(row) == 4 for row in rows)
    run.assembly_up = True  # ps --all showed every component running all the same
    assert bench.profile_rows(run)[0][1] == (
        "failed (try 1: exit 3 after 8.0 s; try 2: not within 240 s), yet ps --all: all running"
    )
    document = bench.document([run])
    assert json.loads(json.dumps(document))["profiles"][0]["profile"] == "wifi"


def test_a_measured_profile_has_every_row_with_its_baseline() -> None:
    run = bench.ProfileRun("lan", rounds=2, up_all_s=12.0, up_all_healthy=True, up_all_tries=1)
    run.assembly_up = True
    run.reach_s = [1.0, 3.0, 2.0, 2.0]
    run.health_ok_after_up_s = 4.0
    run.estop = [bench.ModuleAcks("limb1", "hl-limb-01", [0.02, None], [0.004, 0.005])]
    run.estop_wall_s = [3.0, 3.2]
    run.measured = ["rest", "estop", "outage"]
    run.data_again_s, run.bare_data_again_s = 1.2, 0.4
    run.health_left_ok_s, run.health_ok_again_s = 1.1, 1.5
    run.rest = {"ground1": {"up": 2000.0, "down": 8000.0, "bare_up": 500.0, "bare_down": 500.0}}
    rows = {row[0]: row[1:] for row in bench.profile_rows(run)}
    assert rows["up --all -> healthy"] == ["12.00 s", "2.00 s (reach every robot)", "6.00x"]
    assert rows["estop ack limb1 (hl-limb-01) p50 / p99"] == [
        "20.0 ms / no answer (1 of 2 answered)",
        "4.0 ms / 5.0 ms",
        "5.00x / -",
    ]
    assert rows["data again after 5 s out (hl-limb-01)"] == ["1.20 s", "0.40 s", "3.00x"]
    assert rows["  limb1 health"][0] == (
        "not OK 1.10 s after the cut, OK again 1.50 s after the return"
    )
    run.health_before = ["limb1/health", "limb1/components/joint_manager"]
    again = {row[0]: row[1] for row in bench.profile_rows(run)}
    assert again["  limb1 health"].endswith(
        "(not OK before the cut already: limb1/health and 1 more)"
    )
    run.up_all_tries, run.up_all_failures = 2, ["exit 3 after 8.0 s: no agent answered"]
    assert bench.profile_rows(run)[0][1] == (
        "12.00 s (try 2; try 1: exit 3 after 8.0 s; down --all after each)"
    )
    assert rows["at rest ground1 up / down"] == [
        "2.0 kB/s / 8.0 kB/s",
        "500 B/s / 500 B/s",
        "10.00x",
    ]


def test_without_the_privileges_a_rehearsal_needs_it_says_so_and_exits_2(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import msctl.rehearse.computers as computers

    monkeypatch.setattr(computers, "privileges_problem", lambda: "msctl rehearse needs root")
    assert bench.main(["--profiles", "lan"]) == 2
    assert "msctl rehearse needs root" in capsys.readouterr().err

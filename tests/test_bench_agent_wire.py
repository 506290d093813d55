"""bench/agent_wire.py measures like with like: the hand-written AgentRequest codec and the
canonical one write the same bytes and read the same fields for each case it times."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def _bench() -> Any:
    spec = importlib.util.spec_from_file_location(
        "bench.agent_wire", ROOT / "bench" / "agent_wire.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("bench.agent_wire", module)
    spec.loader.exec_module(module)
    return module


def test_both_paths_agree_on_every_case_and_each_is_timed() -> None:
    bench = _bench()
    cases = bench._cases()
    assert set(cases) == {"ps", "up"}
    bench._check({"hand": bench._hand(), "canon": bench._canonical()}, cases)
    timed = bench.per_call(calls=3, rounds=1)
    assert {c: set(t) for c, t in timed.items()} == {c: {"hand", "canon"} for c in cases}
    assert all(s > 0 for t in timed.values() for s in t.values())

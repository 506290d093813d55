"""Benchmark of the Robot Assembler: how long an operator waits for an assembly.

For each template, in one process and warm (imports done, files in the page cache):

- floor: merely parsing the template, its module type files and their URDFs (tomllib and
  ElementTree, no checks, no caching): the cost of reading the data at all;
- lock+URDF: resolve (every check), compose the URDF, write lock file and URDF atomically;
  "warm" reuses parsed files (the assembler caches them by mtime), "cold" forgets them first;
- MJCF: MuJoCo's URDF import, actuators, ground, compile, XML.

Run: ``python bench/assemble.py [--repeat N]``. Target: dragon_x4 lock+URDF under 50 ms.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

TEMPLATES = ["minimal", "dragon", "dragon_x4", "tricycle", "two_dragons"]
TARGET_MS = 50.0


def _median_ms(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append((time.perf_counter() - start) * 1000)
    return statistics.median(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=30, help="runs per figure (median)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as home:
        # Never touch the operator's real resolution.
        os.environ["MSCTL_HOME"] = home
        from components.assembly import LOCK_NAME, URDF_NAME, encode_lock
        from msctl.assembler import data, resolve
        from msctl.assembler.store import write_assembly

        def floor(name: str) -> None:
            template = tomllib.loads((data.assemblies_dir() / f"{name}.toml").read_text())
            types = {key for slot in template["slots"] for key in slot["fits"]}
            for key in types:
                path = data.modules_dir() / f"{key}.toml"
                module = tomllib.loads(path.read_text())
                ET.parse(path.parent / module["urdf"])
            units = {s.get("default") for s in template["slots"]} - {None}
            for serial in units:
                tomllib.loads((data.calibration_dir() / f"{serial}.toml").read_text())

        def lock_and_urdf(name: str, cold: bool) -> None:
            if cold:
                data.clear_cache()
            resolution = resolve(name)
            write_assembly(
                Path(home) / "assembly",
                {URDF_NAME: resolution.urdf, LOCK_NAME: encode_lock(resolution.lock)},
            )

        resolutions = {name: resolve(name) for name in TEMPLATES}  # warm imports and caches
        resolutions["dragon"].mjcf()  # import mujoco once, outside the figures

        print(
            f"{'template':<12} {'modules':>7} {'floor ms':>9} {'lock+URDF ms':>13} "
            f"{'x floor':>8} {'cold ms':>8} {'MJCF ms':>8}"
        )
        ok = True
        for name in TEMPLATES:
            floor_ms = _median_ms(lambda n=name: floor(n), args.repeat)
            warm_ms = _median_ms(lambda n=name: lock_and_urdf(n, False), args.repeat)
            cold_ms = _median_ms(lambda n=name: lock_and_urdf(n, True), args.repeat)
            mjcf_ms = _median_ms(resolutions[name].mjcf, max(3, args.repeat // 5))
            modules = len(resolutions[name].document["modules"])
            print(
                f"{name:<12} {modules:>7} {floor_ms:>9.2f} {warm_ms:>13.2f} "
                f"{warm_ms / floor_ms:>8.2f} {cold_ms:>8.2f} {mjcf_ms:>8.1f}"
            )
            if name == "dragon_x4":
                ok = warm_ms < TARGET_MS
        data.clear_cache()
    verdict = "meets" if ok else "MISSES"
    print(f"dragon_x4 lock+URDF {verdict} the {TARGET_MS:.0f} ms target")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

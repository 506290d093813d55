"""A limb waving: raise it, swing the wrist a few times with ``lerp``, put it back.

Run against a running assembly (``msctl up dragon`` in simulation, or the real robot)::

    msctl run examples/limb_wave.py [LIMB] [WAVES]

LIMB defaults to the first limb of the assembly, WAVES to 3. Every pose is a ``lerp``: all
the joints named move together, and each command stays within the syncer's ``delta`` of
where the joints are measured.
"""

from __future__ import annotations

import sys

# Joint angles (rad), by joint name without the slot: an arm raised off the ground, then the
# wrist swinging either side. Joints not named keep their place.
RAISED = {"joint2": -0.5, "joint4": 0.6, "joint6": 0.4}
WAVE_LEFT = {"joint5": 0.5}
WAVE_RIGHT = {"joint5": -0.5}
REST = {"joint2": 0.0, "joint4": 0.0, "joint5": 0.0, "joint6": 0.0}


async def main(robot):
    """Wave one limb."""
    slot = sys.argv[1] if len(sys.argv) > 1 else robot.limbs[0]
    waves = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    limb = robot.syncer(slot, speed=0.8)
    start = dict(robot.handler(slot).positions())
    print(f"waving {slot} {waves} times")
    await limb.lerp(RAISED)
    for _ in range(waves):
        await limb.lerp(WAVE_LEFT)
        await limb.lerp(WAVE_RIGHT)
    # Back to where it was, as a whole.
    await limb.lerp({n: start[f"{slot}_{n}"] for n in REST})
    print("done waving")

"""A Dragon driving a square with the wheel helper, its limbs held where they are.

Run against a running Dragon (``msctl up dragon`` in simulation, or the real one)::

    msctl run examples/dragon_square.py [SIDE_M] [SPEED_M_S]

SIDE defaults to 0.4 m, SPEED to 0.2 m/s. The wheel speeds come from the assembly's URDF
(wheel radius, where each wheel sits at the limb tips); every leg of the square ends with
the wheels commanded to 0, and so does Ctrl-C.
"""

from __future__ import annotations

import math
import sys


def main(robot):
    """Drive one square (the synchronous API: every call blocks, motions have wait())."""
    side = float(sys.argv[1]) if len(sys.argv) > 1 else 0.4
    speed = float(sys.argv[2]) if len(sys.argv) > 2 else 0.2
    for limb in robot.limbs:
        robot.handler(limb).hold()  # the wheels sit at the limb tips: keep the limbs still
    drive = robot.drive()
    print(
        f"square of {side} m at {speed} m/s: wheel radius {drive.geometry.wheel_radius:.3f} m, "
        f"track {drive.geometry.track_width:.3f} m"
    )
    for leg in range(4):
        drive.forward(side, speed).wait()
        drive.turn(math.pi / 2, 0.6).wait()
        print(f"leg {leg + 1} done")

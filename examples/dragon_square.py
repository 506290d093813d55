"""A Dragon driving a square by steering its wheel modules with its limbs (crab steering).

Run against a running Dragon (``msctl up dragon`` in simulation, or the real one)::

    msctl run examples/dragon_square.py [SIDE_M] [SPEED_M_S]

SIDE defaults to 0.4 m, SPEED to 0.2 m/s. The body never turns: the limbs point both wheel
modules along a side, the wheels drive the Dragon along it, and so on for the four sides.

Why not turn the body with the wheels? Its wheel modules are 2.6 m apart lengthwise and their
wheels 0.38 m apart across: a skid-steer turn drags the wheels sideways and barely rotates it.

How the limbs steer: lying straight, a limb's pitch joints (2, 4, 6) bend it up and down.
Rolled a quarter turn at its base (joint1) and back at its tip (joint7), the limb keeps its
shape but those joints now turn about the vertical, in the ground plane. Bent a little, the
limb can then turn its wheel module about the module's own centre (``drive.steer_path``
works out the joint angles from the URDF).

Why the square's sides run at 45 degrees to the Dragon: a module turned 90 degrees would put
all four wheels on one line along the body, and the Dragon would tip over sideways. So each
module turns at most 45 degrees either way, and the square is driven diagonally.
"""

from __future__ import annotations

import math
import sys

# Joint angles (rad) of each limb, by joint name without the slot. Both limbs take the same
# angles: limb2 is limb1 turned half a turn about the vertical, so the pose is symmetric.
STRAIGHT = {f"joint{i}": 0.0 for i in range(1, 8)}
UNBENT = {"joint2": 0.0, "joint4": 0.0, "joint6": 0.0}
ROLLED = {**STRAIGHT, "joint1": math.pi / 2, "joint7": -math.pi / 2}
# Bent in the ground plane; the three bends add up to 0, so the modules still face along the
# body, and each module's centre moves about 0.23 m closer in, where it has room to turn.
BENT = {**ROLLED, "joint2": -0.73, "joint4": 1.56, "joint6": -0.83}

# The square's sides: directions in the body's frame (0 is forward, counter-clockwise).
SIDES = [math.radians(a) for a in (45, 135, 225, 315)]


def main(robot):
    """Drive one square (the synchronous API: every call blocks, motions have wait())."""
    side = float(sys.argv[1]) if len(sys.argv) > 1 else 0.4
    speed = float(sys.argv[2]) if len(sys.argv) > 2 else 0.2
    limbs = robot.syncer(*robot.limbs)
    drive = robot.drive()

    def pose(angles):
        """Move every limb to ``angles`` together."""
        limbs.lerp({f"{limb}_{j}": a for limb in robot.limbs for j, a in angles.items()}).wait()

    def steer(direction):
        """Turn every wheel module to roll along ``direction``, in small safe steps."""
        for waypoint in drive.steer_path(direction):
            limbs.lerp(waypoint).wait()

    # From wherever the limbs are: unbend first, then unroll (never both at once).
    for angles in (UNBENT, STRAIGHT, ROLLED, BENT):
        pose(angles)
    print(f"steering joints: {drive.steering_joints()}")
    print(f"square of {side} m at {speed} m/s: driving")
    for leg, direction in enumerate(SIDES):
        steer(direction)
        drive.travel(side, direction, speed).wait()
        print(f"leg {leg + 1} done")
    steer(0.0)
    for angles in (ROLLED, STRAIGHT):
        pose(angles)
    print("square done")

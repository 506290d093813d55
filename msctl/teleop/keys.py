"""The keyboard layouts of ``msctl teleop``, as data: which key moves what, per mode.

Keys are the characters typed for printable keys (``"w"``, ``"W"``, ``","``) and textual's key
names for the rest (``"up"``, ``"tab"``, ``"shift+tab"``). A key not named here, in the mode
at hand, stops the motion (as in teleop_twist_keyboard: "anything else: stop").
"""

from __future__ import annotations

#: The operating modes: jog one joint, move a limb's tip, drive the assembly.
JOINT, IK, DRIVE = "joint", "ik", "drive"
MODES = (JOINT, IK, DRIVE)

#: Keys that switch the mode (every mode).
MODE_KEYS: dict[str, str] = {"1": JOINT, "2": IK, "3": DRIVE}

# ----------------------------------------------------------------------------- joint mode
#: Jog the selected joint: direction of motion.
JOINT_MOVES: dict[str, float] = {"w": 1.0, "s": -1.0}
#: Select a joint within the module (-1 previous, +1 next).
JOINT_SELECT: dict[str, int] = {"up": -1, "down": 1}
#: Select the module (-1 previous, +1 next); also the limb in IK mode.
MODULE_SELECT: dict[str, int] = {"tab": 1, "shift+tab": -1, "right": 1, "left": -1}

# -------------------------------------------------------------------------------- IK mode
#: Tip motion in the limb's base frame (REP 103: x forward, y left, z up): unit linear and
#: angular velocity ``(vx, vy, vz, wx, wy, wz)``. Shifted letters turn, arrows and i/k move.
IK_MOVES: dict[str, tuple[float, float, float, float, float, float]] = {
    "up": (1.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    "down": (-1.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    "left": (0.0, 1.0, 0.0, 0.0, 0.0, 0.0),
    "right": (0.0, -1.0, 0.0, 0.0, 0.0, 0.0),
    "i": (0.0, 0.0, 1.0, 0.0, 0.0, 0.0),
    "k": (0.0, 0.0, -1.0, 0.0, 0.0, 0.0),
    "Q": (0.0, 0.0, 0.0, 1.0, 0.0, 0.0),
    "E": (0.0, 0.0, 0.0, -1.0, 0.0, 0.0),
    "W": (0.0, 0.0, 0.0, 0.0, 1.0, 0.0),
    "S": (0.0, 0.0, 0.0, 0.0, -1.0, 0.0),
    "A": (0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
    "D": (0.0, 0.0, 0.0, 0.0, 0.0, -1.0),
}
#: IK mode selects its limb with these (arrows move the tip).
LIMB_SELECT: dict[str, int] = {"tab": 1, "shift+tab": -1}

# ----------------------------------------------------------------------------- drive mode
#: teleop_twist_keyboard's layout: ``(x, y, th)`` multiplied by (speed, speed, turn).
#: Lower case turns, upper case (shift) moves sideways (holonomic).
DRIVE_MOVES: dict[str, tuple[float, float, float]] = {
    "u": (1.0, 0.0, 1.0),
    "i": (1.0, 0.0, 0.0),
    "o": (1.0, 0.0, -1.0),
    "j": (0.0, 0.0, 1.0),
    "l": (0.0, 0.0, -1.0),
    "m": (-1.0, 0.0, -1.0),
    ",": (-1.0, 0.0, 0.0),
    ".": (-1.0, 0.0, 1.0),
    "U": (1.0, 1.0, 0.0),
    "I": (1.0, 0.0, 0.0),
    "O": (1.0, -1.0, 0.0),
    "J": (0.0, 1.0, 0.0),
    "L": (0.0, -1.0, 0.0),
    "M": (-1.0, 1.0, 0.0),
    "<": (-1.0, 0.0, 0.0),
    ">": (-1.0, -1.0, 0.0),
}
#: The explicit stop of teleop_twist_keyboard (every other unbound key stops too).
DRIVE_STOP = "k"

# ------------------------------------------------------------------------- speed scaling
#: Key -> (factor on the linear speed, factor on the angular speed), as teleop_twist_keyboard.
DRIVE_SPEED: dict[str, tuple[float, float]] = {
    "q": (1.1, 1.1),
    "z": (0.9, 0.9),
    "w": (1.1, 1.0),
    "x": (0.9, 1.0),
    "e": (1.0, 1.1),
    "c": (1.0, 0.9),
}
#: Joint and IK modes scale every speed of the mode together.
SPEED: dict[str, float] = {"q": 1.1, "z": 0.9}

#: Key help per mode, one line each (the app adds the keys every mode shares).
HELP: dict[str, str] = {
    JOINT: "w/s jog  up/down joint  tab/left/right module  q/z speed x1.1/x0.9",
    IK: "arrows x/y  i/k up/down  W/S pitch  A/D yaw  Q/E roll  tab limb  q/z speed",
    DRIVE: "u i o / j k l / m , .  shift: sideways  q/z all  w/x linear  e/c angular",
}
#: The keys every mode shares.
COMMON_HELP = "1 joint  2 ik  3 drive  space E-STOP  ctrl+r recover  esc/ctrl+c stop+quit"

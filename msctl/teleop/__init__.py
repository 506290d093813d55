"""``msctl teleop``: keyboard teleoperation of a running assembly, with a deadman.

The parts, from keys to wire:

* :mod:`msctl.teleop.keys`: the layouts, as data;
* :mod:`msctl.teleop.core`: the pure core (deadman, key -> command, speeds, rate, one stop);
* :mod:`msctl.teleop.wire`: what puts a command on the data plane (joint jog through the joint
  manager, tip motion through the IK syncer, Twist on ``cmd_vel``);
* :mod:`msctl.teleop.operator`: the core run on its own thread with the real clock;
* :mod:`msctl.teleop.link`: the connection to the running assembly;
* :mod:`msctl.teleop.app`: the textual screen.
"""

"""Dynamixel Protocol 2.0 backend (G-line robots): one serial chain of X-series servos.

One job per module:

- :mod:`.control_table`: the X-series control table and the meaning of its values;
- :mod:`.units`: the servo models' constants and the one conversion to SI units;
- :mod:`.servo`: what the backend knows of one servo;
- :mod:`.port`: the serial port and the exchanges on it;
- :mod:`.bringup`: pinging a servo and bringing it up (mode, goal, torque);
- :mod:`.watchdog`: the servos' Bus Watchdog, armed, fed and checked;
- :mod:`.cycle`: one I/O step's bus work: the read cycle, the queued goals, a halt;
- :mod:`.diagnostics`: what a servo's and the bus's state mean to an operator;
- :mod:`.backend`: :class:`~.backend.DynamixelBackend`, the I/O thread that ties them.
"""

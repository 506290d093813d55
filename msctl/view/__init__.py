"""``msctl view`` and ``msctl bag view``: the robot in 3D, composed at the operator's end.

- :mod:`~msctl.view.scene`: the Core (URDF shapes, forward kinematics, looks by health);
- :mod:`~msctl.view.live`: the scene fed from the data plane;
- :mod:`~msctl.view.bag`: the scene fed from a recorded bag, at its recorded times;
- :mod:`~msctl.view.rerun_sink`: draws it with rerun (web viewer, ``.rrd``);
- :mod:`~msctl.view.foxglove_server`: serves it to Foxglove (live);
- :mod:`~msctl.view.bag_foxglove` and :mod:`~msctl.view.playback`: a bag played to Foxglove
  over its time range, its playback bar moving a playhead (the Core).
"""

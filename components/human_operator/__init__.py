"""Human operator: a ground station's operator-side process (``msctl teleop`` is its screen).

It holds the claims of the modules its operators command (:mod:`components.claims`), and
relays their commands (``joint_set``, ``cmd_vel``) with a deadman of its own: when a relayed
stream of motion commands stops (the screen froze, its link dropped), exactly one stop goes
out within the timeout, then nothing. Its node shows the station's operator on the graph.

* :mod:`~components.human_operator.routes`: which topics it relays, from the assembly;
* :mod:`~components.human_operator.core`: the relay and its deadman (pure);
* :mod:`~components.human_operator.desk`: the claims and who may use which relay (I/O);
* :mod:`~components.human_operator.build`: the builder;
* :mod:`~components.human_operator.client`: how a screen attaches to it.
"""

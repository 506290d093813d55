"""How the human operator meets the data plane through its executor.

It publishes each route's target (``/limb1/joint_set``, ``/cmd_vel``: absolute) and its
status on ``diagnostics`` (relative to its station's namespace), and ticks its deadman fast
enough that a stop goes out within a tick of the timeout. The relay inputs are not in this
spec: who may publish on them changes as screens attach (the desk subscribes them, see
:mod:`~components.human_operator.desk`).
"""

from __future__ import annotations

from collections.abc import Sequence

from components.executor.interface import Every, InterfaceSpec, Publish
from components.human_operator.routes import Route
from components.messages import DIAGNOSTIC_ARRAY

#: Seconds between deadman checks: a stop goes out at most this late after the timeout.
TICK_PERIOD = 0.02


def human_operator_interface(routes: Sequence[Route]) -> InterfaceSpec:
    """The interface of a human operator relaying ``routes``."""
    return InterfaceSpec(
        publish=(
            *(Publish(route.target, route.msg_type) for route in routes),
            Publish("diagnostics", DIAGNOSTIC_ARRAY),
        ),
        every=(Every(TICK_PERIOD, "tick"),),
    )

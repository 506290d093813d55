"""The autonomous operator kind: a supervised Python-API script, ``main(robot, **params)``."""

from components.kinds import ComponentKind, Placement

KIND = ComponentKind(
    name="autonomous_operator",
    summary="a supervised Python-API script, main(robot): steering, posture, guardian...",
    placement=Placement.STATION,
    config=("components.autonomous_operator.core:OperatorConfig",),
    builder="components.autonomous_operator.build:build",
    interface="components.autonomous_operator.interface:AUTONOMOUS_OPERATOR",
    healthy_output="diagnostics",
    structural=("script", "robot", "params"),
    checks={"script": "components.autonomous_operator.script:check_script"},
    validate="components.autonomous_operator.script:validate",
    # A station's operators: its scripts forward the holders' commands (the steering's
    # cmd_vel, taken only from the claim's holder) or act for the station (posture); a
    # module's joint managers take their commands as they take the holder's.
    claim_relay=True,
    own_process=True,
    named=True,
    # The API's IK (its random restarts) and its thread pool, loaded on first use.
    preload=("numpy.random", "concurrent.futures.thread"),
    not_rebuilt_alone="its script runs in its own process: restart it whole",
)

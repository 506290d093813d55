"""The data archiver kind: the recorder (``msctl record``) as a supervised ground-station
component, recording what the station's data says into rosbag2 (MCAP) bags."""

from components.kinds import ComponentKind, Placement

KIND = ComponentKind(
    name="data_archiver",
    summary="records the data plane to rosbag2 (MCAP) bags; its status on diagnostics",
    placement=Placement.STATION,
    config=("components.data_archiver.core:ArchiverConfig",),
    builder="components.data_archiver.build:build",
    interface="components.data_archiver.interface:DATA_ARCHIVER",
    healthy_output="diagnostics",
    # Recording is buffered: a burst written milliseconds later loses nothing.
    niceness=10,
    # The recorder's writer (MCAP, its compressors) and its metadata's YAML.
    preload=("components.recording.recorder", "components.recording.writer", "mcap.writer", "yaml"),
)

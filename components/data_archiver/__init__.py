"""The data archiver: the recorder run as a supervised ground-station component, writing
rosbag2 (MCAP) bags of what the station's data says to record (see ``kind.py``)."""

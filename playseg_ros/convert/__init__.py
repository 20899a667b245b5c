"""`playseg convert`: robot bags (rosbag2 mcap/sqlite3, ROS 1) through a mapping into a playseg dataset.

mapping.py (the YAML mapping), source.py (reading bags through rosbags), alignment.py (other topics onto
the step clock), decode.py (messages to feature rows), annotations.py (time labels to segments), build.py
(one bag to episodes), segmenting.py (``--segment``: a model labels the unannotated episodes), run.py (many bags, a process pool, resuming, merging), inspect.py (``--inspect``).
See docs/convert.md.
"""

from playseg_ros.convert.errors import ConvertError, MappingError
from playseg_ros.convert.inspect import inspect_text
from playseg_ros.convert.mapping import ConvertMapping, load_mapping
from playseg_ros.convert.run import BagReport, ConvertSummary, convert
from playseg_ros.convert.segmenting import SegmentationSpec

__all__ = [
    "BagReport",
    "ConvertError",
    "ConvertMapping",
    "ConvertSummary",
    "MappingError",
    "SegmentationSpec",
    "convert",
    "inspect_text",
    "load_mapping",
]

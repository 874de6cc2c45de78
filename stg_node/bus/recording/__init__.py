"""Recording and replaying the bus: MCAP files in the stg-bus format (proto/recording.md).

    from stg_node.bus.recording import BagReader, Player, Recorder

    with Recorder("session.mcap", config=bus_config) as recorder:   # start() ... stop()
        while running:
            recorder.poll(0.2)
    for msg in BagReader("session.mcap").messages():                 # header + buffers, exactly
        env = msg.envelope()
    Player(BagReader("session.mcap"), config=bus_config, rate=1.0).run()

``stg-bag`` (stg_node/cli/bag.py) is the command line; docs/RECORDING.md the guide. Like
the rest of the bus this package never imports torch; OpenCV and the Foxglove schemas are
imported only by the exports that need them.
"""

from stg_node.bus.recording.format import MESSAGE_ENCODING, SCHEMA_ENCODING, RecordingError
from stg_node.bus.recording.info import BagInfo, bag_info, format_info
from stg_node.bus.recording.player import Lockstep, PlaybackError, Player, PlayStats
from stg_node.bus.recording.reader import BagFile, BagReader, RecordedMessage, read_messages
from stg_node.bus.recording.recorder import Recorder, RecorderStats
from stg_node.bus.recording.writer import COMPRESSIONS, BagWriter

__all__ = [
    "COMPRESSIONS",
    "MESSAGE_ENCODING",
    "SCHEMA_ENCODING",
    "BagFile",
    "BagInfo",
    "BagReader",
    "BagWriter",
    "Lockstep",
    "PlayStats",
    "PlaybackError",
    "Player",
    "RecordedMessage",
    "Recorder",
    "RecorderStats",
    "RecordingError",
    "bag_info",
    "format_info",
    "read_messages",
]

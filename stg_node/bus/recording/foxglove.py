"""View channels for Foxglove: a copy of a recording that Foxglove can show, not just list.

    export_foxglove(BagReader("session.mcap"), "session.view.mcap")

Foxglove opens an stg-bus recording but sees each message as opaque bytes (it does not
know the ``stg-bus`` encoding). This export writes a new MCAP file holding the original
channels unchanged (so the file still plays back with ``stg-bag play``) plus, for each
message, view channels in Foxglove's own schemas. The conversions, and the table of view
channels, live in :mod:`stg_node.bus.foxglove_views`, which the live ``foxglove`` node uses
too: a recording exported here and the live session show the same channels.

Why at export and not at record time: encoding views (JPEG of a 1080p frame: ~10 ms)
would cost the recorder CPU on the hot path and risk drops, and the recording stays
exactly what crossed the bus. Why protobuf for images: binary bytes (JSON would need
base64, a third larger and slow), and the schemas come with Foxglove's own SDK
(each a FileDescriptorSet).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from stg_node.bus.foxglove_views import IMAGE_FORMATS, fields_json_schema, message_views
from stg_node.bus.recording.format import RecordingError
from stg_node.bus.recording.mcapfile import COMPRESSIONS, McapFile
from stg_node.bus.recording.reader import BagReader
from stg_node.progress import progress


@dataclass
class FoxgloveStats:
    messages: int = 0  # original messages copied
    views: dict[str, int] = field(default_factory=dict)  # view channel -> messages
    out: str = ""


def export_foxglove(
    reader: BagReader,
    out: str | Path,
    *,
    topics=None,
    image_format: str = "jpeg",
    jpeg_quality: int = 90,
    compression: str = "zstd",
    keep_original: bool = True,
    show_progress: bool = True,
) -> FoxgloveStats:
    """Write ``out``: the recording's messages (``keep_original``) plus Foxglove view channels."""
    from stg_node.bus.recording.format import MESSAGE_ENCODING, META_END, SCHEMA_ENCODING  # noqa: PLC0415
    from stg_node.bus.recording.schemas import schema_data  # noqa: PLC0415

    if image_format not in IMAGE_FORMATS:
        raise RecordingError(f"image format {image_format!r} is not one of {IMAGE_FORMATS}")
    if compression not in COMPRESSIONS:
        raise RecordingError(f"compression {compression!r} is not one of {list(COMPRESSIONS)}")
    try:
        import foxglove.messages  # noqa: F401, PLC0415
    except ImportError as exc:
        raise RecordingError(f"the Foxglove export needs foxglove-sdk ({exc})") from exc
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stats = FoxgloveStats(out=str(out))
    types = reader.types()
    total = reader.message_count
    with open(out, "wb") as f:
        writer = McapFile(f, compression=compression)
        writer.start(profile="", library="stg_node stg-bag export --foxglove")
        schemas: dict[str, int] = {}
        channels: dict[str, int] = {}

        def schema_id(name: str, encoding: str, data: bytes) -> int:
            if name not in schemas:
                schemas[name] = writer.register_schema(name, encoding, data)
            return schemas[name]

        def channel(topic: str, encoding: str, sid: int, meta: dict | None = None) -> int:
            if topic not in channels:
                channels[topic] = writer.register_channel(topic, encoding, sid, meta or {})
            return channels[topic]

        for bag in reader.files:
            for name, meta in bag.metadata.items():
                if name != META_END:  # its counts describe the source file, not this one
                    writer.add_metadata(name, meta)
        with progress(total=total, desc="foxglove views", unit="msg", enabled=show_progress) as bar:
            for msg in reader.messages(topics):
                bar.update(1)
                env = msg.envelope()
                if keep_original:
                    type_name = types.get(msg.topic, env.type)
                    yaml_schema = schema_data(type_name)
                    sid = schema_id(type_name, SCHEMA_ENCODING, yaml_schema) if yaml_schema is not None else 0
                    cid = channel(msg.topic, MESSAGE_ENCODING, sid, {"type": type_name})
                    writer.add_message(cid, msg.log_time_ns, msg.publish_time_ns, msg.sequence, [msg.data])
                    stats.messages += 1
                views = message_views(
                    env.topic, env.header, env.arrays, image_format=image_format, jpeg_quality=jpeg_quality
                )
                for view_topic, view in views:
                    if isinstance(view, bytes):
                        name = f"stg.{env.type}.fields"
                        sid = schemas.get(name) or schema_id(
                            name, "jsonschema", json.dumps(fields_json_schema(env.type)).encode()
                        )
                        cid = channel(view_topic, "json", sid)
                        data = view
                    else:
                        schema = view.get_schema()
                        sid = schemas.get(schema.name) or schema_id(schema.name, schema.encoding, schema.data)
                        cid = channel(view_topic, schema.encoding, sid)
                        data = view.encode()
                    writer.add_message(cid, msg.log_time_ns, msg.publish_time_ns, msg.sequence, [data])
                    stats.views[view_topic] = stats.views.get(view_topic, 0) + 1
        writer.finish()
    return stats

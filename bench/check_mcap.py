#!/usr/bin/env python3
"""Independent check of a flownav MCAP log with the official `mcap` Python package (1.x).

Reads the file with a reader flownav did not write and checks:
  - the summary (statistics, channels, schemas) is present and agrees with the messages;
  - every channel has a topic starting with '/', a known schema name for its topic, schema
    encoding 'jsonschema' (a JSON object whose title is the schema name) and message encoding 'json';
  - per-channel message counts (optionally against --expect TOPIC=N);
  - per-channel time order: log_time non-decreasing, publish_time == log_time, sequence increasing;
  - every message is a JSON object; images decode (base64) to the advertised size.

With --truncated (a log whose writer was killed): no summary is expected; the messages are read
up to the last complete chunk, the cut after it is reported, and at least one message must be read.

Usage:  python3 bench/check_mcap.py FILE [--expect /camera/image=90 ...] [--require-all-topics] [--truncated]
Setup:  python3 -m venv .venv-mcap && .venv-mcap/bin/pip install 'mcap==1.*'
Exit status 0 when every check passes; each failure is printed on its own line.
"""

import argparse
import base64
import json
import sys
from collections import defaultdict

from mcap.reader import NonSeekingReader, make_reader

# topic -> accepted schema names (the table in docs/logging.md)
TOPICS = {
    "/camera/image": {"foxglove.CompressedImage", "foxglove.RawImage"},
    "/camera/calibration": {"foxglove.CameraCalibration"},
    "/flow/annotations": {"foxglove.ImageAnnotations"},
    "/flow/field": {"flownav.FlowField"},
    "/offis/perception": {"flownav.Perception"},
    "/pafsis/goal": {"flownav.Goal"},
    "/control/setpoint": {"flownav.Setpoint"},
    "/base/odometry": {"flownav.Odometry"},
    "/base/status": {"flownav.BaseStatus"},
    "/tf": {"foxglove.FrameTransform"},
    "/sim/world": {"foxglove.SceneUpdate"},
    "/log": {"foxglove.Log"},
    "/logger/stats": {"flownav.LoggerStats"},
    "/step/input": {"flownav.StepInput"},
}
OPTIONAL = {"/logger/stats", "/step/input"}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("file")
    ap.add_argument("--expect", action="append", default=[], metavar="TOPIC=N", help="expected message count")
    ap.add_argument("--require-all-topics", action="store_true", help="every flownav topic must be present")
    ap.add_argument("--truncated", action="store_true", help="a killed writer's file: no summary, read to the cut")
    args = ap.parse_args()
    errors = []

    counts = defaultdict(int)
    last_time = {}
    last_seq = {}
    channels = {}
    with open(args.file, "rb") as f:
        # A truncated file has no footer to seek to: read it front to back.
        # (a non-seeking reader answers one query: the header comes from a reader of its own).
        if args.truncated:
            with open(args.file, "rb") as g:
                header = NonSeekingReader(g).get_header()
            reader = NonSeekingReader(f)
        else:
            reader = make_reader(f)
            header = reader.get_header()
        try:
            summary = None if args.truncated else reader.get_summary()
        except Exception as e:  # a truncated file: the official reader gives up here
            summary = None
            if not args.truncated:
                errors.append(f"cannot read the summary: {type(e).__name__}: {e}")
        if summary is None and not errors and not args.truncated:
            errors.append("no summary section (file not closed cleanly?)")
        if summary is not None and args.truncated:
            errors.append("--truncated: the file has a summary (it was closed cleanly)")
        try:
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                check_message(schema, channel, message, counts, last_time, last_seq, channels, errors)
        except Exception as e:
            cut = f"reading stopped after {sum(counts.values())} messages: {type(e).__name__}: {e}"
            if args.truncated:
                print(f"cut (expected): {cut}")
            else:
                errors.append(cut)
        if args.truncated and not counts:
            errors.append("--truncated: no complete message before the cut")

    report(args, header, summary, counts, channels, errors)
    return 0 if not errors else 1


def check_message(schema, channel, message, counts, last_time, last_seq, channels, errors):
    """Checks one message; records its channel, count, time and sequence."""
    cid = channel.id
    if cid not in channels:
        channels[cid] = (channel, schema)
    counts[cid] += 1
    where = f"{channel.topic} message #{counts[cid]} (log_time {message.log_time})"
    if cid in last_time and message.log_time < last_time[cid]:
        errors.append(f"{where}: log_time goes back from {last_time[cid]}")
    last_time[cid] = message.log_time
    if message.publish_time != message.log_time:
        errors.append(f"{where}: publish_time {message.publish_time} != log_time")
    if cid in last_seq and message.sequence <= last_seq[cid]:
        errors.append(f"{where}: sequence {message.sequence} does not increase")
    last_seq[cid] = message.sequence
    try:
        body = json.loads(message.data)
    except ValueError as e:
        errors.append(f"{where}: not JSON: {e}")
        return
    if not isinstance(body, dict):
        errors.append(f"{where}: JSON is not an object")
        return
    name = schema.name if schema else ""
    if name in ("foxglove.RawImage", "foxglove.CompressedImage"):
        data = base64.b64decode(body["data"], validate=True)
        if name == "foxglove.RawImage" and len(data) != body["step"] * body["height"]:
            errors.append(f"{where}: {len(data)} bytes, expected step*height {body['step'] * body['height']}")
        if name == "foxglove.CompressedImage" and not data.startswith(b"\xff\xd8"):
            errors.append(f"{where}: data is not a JPEG (no SOI marker)")


def report(args, header, summary, counts, channels, errors):
    """Checks channels, schemas and counts against the summary and --expect; prints the result."""
    topics_seen = set()
    for cid, (channel, schema) in sorted(channels.items()):
        topics_seen.add(channel.topic)
        name = schema.name if schema else "(none)"
        if not channel.topic.startswith("/"):
            errors.append(f"channel {cid}: topic {channel.topic!r} does not start with '/'")
        if channel.topic in TOPICS and name not in TOPICS[channel.topic]:
            errors.append(f"{channel.topic}: schema {name}, expected one of {sorted(TOPICS[channel.topic])}")
        if channel.message_encoding != "json":
            errors.append(f"{channel.topic}: message encoding {channel.message_encoding!r}, expected 'json'")
        if schema is None or schema.encoding != "jsonschema":
            errors.append(f"{channel.topic}: schema encoding is not 'jsonschema'")
        else:
            try:
                js = json.loads(schema.data)
                if js.get("title") != schema.name or js.get("type") != "object":
                    errors.append(f"{channel.topic}: JSON schema title/type mismatch ({js.get('title')!r})")
            except ValueError as e:
                errors.append(f"{channel.topic}: schema data is not JSON: {e}")

    if summary is not None:
        stats = summary.statistics
        if stats is None:
            errors.append("summary has no statistics record")
        else:
            total = sum(counts.values())
            if stats.message_count != total:
                errors.append(f"statistics say {stats.message_count} messages, read {total}")
            for cid, n in counts.items():
                if stats.channel_message_counts.get(cid, 0) != n:
                    errors.append(f"channel {cid}: statistics say {stats.channel_message_counts.get(cid)}, read {n}")
        for cid in channels:
            if cid not in summary.channels:
                errors.append(f"channel {cid} missing from the summary")

    per_topic = defaultdict(int)
    for cid, n in counts.items():
        per_topic[channels[cid][0].topic] += n
    for spec in args.expect:
        topic, _, n = spec.partition("=")
        if per_topic.get(topic, 0) != int(n):
            errors.append(f"{topic}: {per_topic.get(topic, 0)} messages, expected {n}")
    if args.require_all_topics:
        for topic in sorted(set(TOPICS) - OPTIONAL - topics_seen):
            errors.append(f"topic {topic} missing")

    print(f"{args.file}: library {header.library!r}, {len(channels)} channels, {sum(counts.values())} messages")
    for topic in sorted(per_topic):
        schemas = sorted({(s.name if s else "") for c, s in channels.values() if c.topic == topic})
        print(f"  {topic:22} {','.join(schemas):28} {per_topic[topic]:7}")
    for e in errors:
        print(f"FAIL: {e}")
    print("check_mcap: OK" if not errors else f"check_mcap: {len(errors)} problem(s)")


if __name__ == "__main__":
    sys.exit(main())

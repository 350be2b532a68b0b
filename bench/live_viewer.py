#!/usr/bin/env python3
"""A headless Foxglove viewer for `flownav run|sim --live`: connects with the `foxglove.sdk.v1`
subprotocol, subscribes to every channel as it is advertised, and counts what arrives, so the
live view's cost can be measured with a client as demanding as Foxglove (every topic).

    python3 -m venv /tmp/venv-ws && /tmp/venv-ws/bin/pip install -q websocket-client
    /tmp/venv-ws/bin/python bench/live_viewer.py ws://127.0.0.1:8765 [--seconds S] [--check]

Retries the connection until the server is up (up to 30 s), reads until the server goes away or
--seconds pass, then prints one JSON line: messages and bytes per `topic schema`.
"""

import argparse
import json
import struct
import sys
import time

import websocket


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("url")
    ap.add_argument("--seconds", type=float, default=None, help="stop after this long")
    ap.add_argument("--check", action="store_true", help="parse every payload as JSON (costs CPU)")
    args = ap.parse_args()

    deadline = time.monotonic() + 30
    while True:
        try:
            ws = websocket.create_connection(args.url, subprotocols=["foxglove.sdk.v1"], timeout=1)
            break
        except (ConnectionError, OSError):
            if time.monotonic() > deadline:
                print(f"live_viewer: cannot connect to {args.url}", file=sys.stderr)
                return 1
            time.sleep(0.1)

    channels = {}  # channel id -> "topic schema"
    subscriptions = {}  # subscription id -> channel id
    counts = {}
    nbytes = {}
    start = time.monotonic()
    while args.seconds is None or time.monotonic() - start < args.seconds:
        try:
            opcode, data = ws.recv_data()
        except websocket.WebSocketTimeoutException:
            continue
        except (websocket.WebSocketConnectionClosedException, ConnectionError, OSError):
            break
        if opcode == websocket.ABNF.OPCODE_TEXT:
            msg = json.loads(data)
            if msg.get("op") == "advertise":
                subs = []
                for ch in msg["channels"]:
                    sub = len(subscriptions) + 1
                    subscriptions[sub] = ch["id"]
                    channels[ch["id"]] = f'{ch["topic"]} {ch["schemaName"]}'
                    subs.append({"id": sub, "channelId": ch["id"]})
                ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        elif opcode == websocket.ABNF.OPCODE_BINARY and data[:1] == b"\x01":
            sub, _log_time = struct.unpack_from("<IQ", data, 1)
            key = channels[subscriptions[sub]]
            if args.check:
                json.loads(data[13:])
            counts[key] = counts.get(key, 0) + 1
            nbytes[key] = nbytes.get(key, 0) + len(data) - 13
        elif opcode == websocket.ABNF.OPCODE_CLOSE:
            break
    print(json.dumps({"seconds": round(time.monotonic() - start, 2), "messages": counts, "bytes": nbytes}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

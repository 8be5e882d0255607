"""A Sparkplug B host written with a third-party library (pysparkplug)
that follows one metric of one device as a SCADA's tag would: its value
from the DBIRTH, then from every DDATA that carries it.

Usage: sparkplug_follow.py PORT GROUP NODE DEVICE METRIC

Connects to the broker on 127.0.0.1:PORT, subscribes to the group, asks
the node for a rebirth (NCMD Node Control/Rebirth), and prints a JSON line
{"kind": ..., "value": ...} each time the tag's value is set, until its
standard input closes. Exits 2 without a connection within 10 s.
"""

import json
import sys
import threading

import pysparkplug as psp


def main() -> int:
    port, group, node, device, metric = (
        int(sys.argv[1]),
        sys.argv[2],
        sys.argv[3],
        sys.argv[4],
        sys.argv[5],
    )
    connected = threading.Event()

    def on_message(_client, message):
        kind = str(message.topic.message_type)
        if message.topic.device_id != device or kind not in ("DBIRTH", "DDATA"):
            return
        for m in getattr(message.payload, "metrics", ()):
            if m.name == metric:
                print(json.dumps({"kind": kind, "value": m.value}), flush=True)

    client = psp.Client(client_id="pysparkplug-follower")
    client.connect(
        "127.0.0.1", port=port, blocking=False, callback=lambda _c: connected.set()
    )
    if not connected.wait(10):
        print("no connection to the broker within 10 s", file=sys.stderr)
        return 2
    client.subscribe(
        psp.Topic(group_id=group, message_type=psp.MULTI_LEVEL_WILDCARD),
        psp.QoS.AT_LEAST_ONCE,
        on_message,
    )
    rebirth = psp.NCmd(
        timestamp=psp.get_current_timestamp(),
        metrics=(
            psp.Metric(
                timestamp=psp.get_current_timestamp(),
                name="Node Control/Rebirth",
                datatype=psp.DataType.BOOLEAN,
                value=True,
            ),
        ),
    )
    client.publish(
        psp.Message(
            topic=psp.Topic(
                group_id=group, message_type=psp.MessageType.NCMD, edge_node_id=node
            ),
            payload=rebirth,
            qos=psp.QoS.AT_LEAST_ONCE,
            retain=False,
        ),
        include_dtypes=True,
    )
    sys.stdin.read()
    client.disconnect()
    return 0


if __name__ == "__main__":
    sys.exit(main())

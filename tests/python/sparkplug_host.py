"""A Sparkplug B host written with a third-party library (pysparkplug), to
check that what drivegate publishes decodes outside the project.

Usage: sparkplug_host.py PORT GROUP NODE DEVICES

Connects to the broker on 127.0.0.1:PORT, subscribes to the group, asks
the node for a rebirth (NCMD Node Control/Rebirth) and prints each
message it decodes as a JSON line, until it has the NBIRTH and DEVICES
DBIRTHs. Exits 2 when that takes more than 20 s.
"""

import json
import sys
import threading
import time

import pysparkplug as psp


def main() -> int:
    port, group, node, devices = (
        int(sys.argv[1]),
        sys.argv[2],
        sys.argv[3],
        int(sys.argv[4]),
    )
    connected = threading.Event()
    done = threading.Event()
    births = {"NBIRTH": 0, "DBIRTH": 0}

    def on_message(_client, message):
        kind = str(message.topic.message_type)
        payload = message.payload
        metrics = getattr(payload, "metrics", None)
        if metrics is None:
            metrics = (payload.bd_seq_metric,)
        record = {
            "type": kind,
            "node": message.topic.edge_node_id,
            "device": message.topic.device_id,
            "seq": getattr(payload, "seq", None),
            "metrics": {
                m.name: {"datatype": m.datatype.name, "value": m.value}
                for m in metrics
            },
        }
        print(json.dumps(record), flush=True)
        if kind in births:
            births[kind] += 1
        if births["NBIRTH"] >= 1 and births["DBIRTH"] >= devices:
            done.set()

    client = psp.Client(client_id="pysparkplug-host")
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
    # Published after the subscription on the same connection: the broker
    # has the subscription in place before the node answers.
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
    ok = done.wait(20)
    client.disconnect()
    time.sleep(0.1)
    return 0 if ok else 2


if __name__ == "__main__":
    sys.exit(main())

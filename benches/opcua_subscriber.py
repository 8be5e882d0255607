"""One OPC UA session of the OPC UA benchmark (benches/opcua.rs), on asyncua:
monitors every variable of every drive (Objects/Drives/*/*, sampling 0: the
server's minimum, the poll period; queue 10) in a subscription publishing
every --publishing-ms (default 0: the server's least, the poll period), and
after --warmup seconds counts, for
--seconds, the notifications and their latency: the client's clock when a
notification is handled minus the value's source timestamp (the poll's
time; same machine, same clock). Prints one JSON line.

    python3 opcua_subscriber.py URL --seconds 10 --warmup 3
"""

import argparse
import asyncio
import json
import time

from asyncua import Client, ua

NS = "urn:drivegate:drives"


class Handler:
    def __init__(self):
        self.counting = False
        self.count = 0
        self.latencies = []

    def datachange_notification(self, node, val, data):
        if not self.counting:
            return
        self.count += 1
        src = data.monitored_item.Value.SourceTimestamp
        if src is not None:
            self.latencies.append(time.time() * 1000.0 - src.timestamp() * 1000.0)


async def main():
    p = argparse.ArgumentParser()
    p.add_argument("url")
    p.add_argument("--seconds", type=float, default=10)
    p.add_argument("--warmup", type=float, default=3)
    p.add_argument("--publishing-ms", type=float, default=0)
    args = p.parse_args()
    async with Client(args.url, timeout=60) as c:
        ns = await c.get_namespace_index(NS)
        drives = await c.nodes.objects.get_child(f"{ns}:Drives")
        nodes = []
        for d in await drives.get_children():
            for n in await d.get_children(nodeclassmask=ua.NodeClass.Variable):
                nodes.append(n)
        h = Handler()
        sub = await c.create_subscription(
            ua.CreateSubscriptionParameters(RequestedPublishingInterval=args.publishing_ms, RequestedMaxKeepAliveCount=100, MaxNotificationsPerPublish=0, PublishingEnabled=True, Priority=0),
            h,
        )
        for i in range(0, len(nodes), 200):
            await sub.subscribe_data_change(nodes[i : i + 200], sampling_interval=0, queuesize=10)
        await asyncio.sleep(args.warmup)
        h.counting = True
        t0 = time.monotonic()
        await asyncio.sleep(args.seconds)
        h.counting = False
        elapsed = time.monotonic() - t0
        lat = sorted(h.latencies)
        q = lambda f: lat[min(len(lat) - 1, int(f * len(lat)))] if lat else None
        print(json.dumps({
            "items": len(nodes),
            "publishing_ms": sub.parameters.RequestedPublishingInterval,
            "notifications": h.count,
            "per_second": h.count / elapsed,
            "p50_ms": q(0.5),
            "p99_ms": q(0.99),
            "max_ms": lat[-1] if lat else None,
        }), flush=True)


if __name__ == "__main__":
    asyncio.run(main())

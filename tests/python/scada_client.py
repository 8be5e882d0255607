#!/usr/bin/env python3
"""A SCADA over Modbus TCP that models each drive as a device of its own,
with a TCP connection per device (as Ignition's Modbus TCP driver and
Kepware's default socket usage do): pymodbus, driven line by line.

Usage: scada_client.py HOST PORT SOURCE UNITS

Opens UNITS connections from the local address SOURCE (any 127.x.y.z on
Linux), one per unit 1..UNITS, all at once, and answers with one JSON line:
{"connected": n, "failed": [unit, ...]}. Then reads commands on stdin, one
per line, each answered with one JSON line on stdout:

  round    every connection reads its unit's status block (0x03 at 0xC0,
           7 registers) at once        {"answered": n, "failed": {unit: why},
                                        "slowest_ms": ms}
  close    closes every connection     {"closed": n}

Needs pymodbus 3.10 or later (`device_id=`). Exit status 3 when pymodbus
is missing.
"""

import asyncio
import json
import sys
import time

try:
    from pymodbus.client import AsyncModbusTcpClient
    from pymodbus.exceptions import ModbusException
except ImportError:
    print(
        "pymodbus is not installed: install it with `pip install 'pymodbus>=3.10'`",
        file=sys.stderr,
    )
    sys.exit(3)


def say(obj):
    print(json.dumps(obj), flush=True)


async def read(unit, client):
    started = time.monotonic()
    try:
        rr = await client.read_holding_registers(0xC0, count=7, device_id=unit)
    except (ModbusException, OSError) as e:
        return unit, str(e), 0.0
    ms = (time.monotonic() - started) * 1000
    if rr.isError():
        return unit, f"exception {getattr(rr, 'exception_code', None)}", ms
    if len(rr.registers) != 7:
        return unit, f"{len(rr.registers)} registers", ms
    return unit, None, ms


async def main():
    if len(sys.argv) != 5:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    host, port, source, units = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
    clients = {
        u: AsyncModbusTcpClient(
            host, port=port, timeout=10, retries=0, source_address=(source, 0)
        )
        for u in range(1, units + 1)
    }
    await asyncio.gather(*(c.connect() for c in clients.values()))
    failed = [u for u, c in clients.items() if not c.connected]
    say({"connected": units - len(failed), "failed": failed})
    loop = asyncio.get_running_loop()
    while True:
        line = await loop.run_in_executor(None, sys.stdin.readline)
        command = line.strip()
        if command == "round":
            results = await asyncio.gather(*(read(u, c) for u, c in clients.items()))
            bad = {str(u): why for u, why, _ in results if why is not None}
            slowest = max((ms for _, _, ms in results), default=0.0)
            say({"answered": len(results) - len(bad), "failed": bad, "slowest_ms": round(slowest, 1)})
        elif command in ("close", ""):
            for c in clients.values():
                c.close()
            say({"closed": len(clients)})
            return
        else:
            say({"error": f"unknown command {command}"})


if __name__ == "__main__":
    asyncio.run(main())

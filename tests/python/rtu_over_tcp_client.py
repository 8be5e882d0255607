#!/usr/bin/env python3
"""A third-party Modbus RTU-over-TCP master (pymodbus) for drivegate's tests:
what a SCADA package does with a serial device server in raw socket mode.

Usage: rtu_over_tcp_client.py HOST PORT UNIT ADDRESS COUNT

Reads COUNT holding registers (0x03) from UNIT, framing the request and the
reply as RTU (CRC, no MBAP header) over the TCP connection. Prints one JSON
object: {"registers": [...]}, {"exception": n} or {"error": "..."}; exit
status 3 when pymodbus is missing.
"""

import json
import sys

try:
    from pymodbus import FramerType
    from pymodbus.client import ModbusTcpClient
    from pymodbus.exceptions import ModbusException
except ImportError:
    print(
        "pymodbus is not installed: install it with `pip install 'pymodbus>=3.10'`",
        file=sys.stderr,
    )
    sys.exit(3)


def main():
    host, port, unit, address, count = sys.argv[1:6]
    client = ModbusTcpClient(
        host, port=int(port), framer=FramerType.RTU, timeout=3, retries=0
    )
    if not client.connect():
        print(json.dumps({"error": f"cannot connect to {host}:{port}"}))
        return
    try:
        rr = client.read_holding_registers(
            int(address, 0), count=int(count, 0), device_id=int(unit, 0)
        )
        if rr.isError():
            print(json.dumps({"exception": getattr(rr, "exception_code", None)}))
        else:
            print(json.dumps({"registers": list(rr.registers)}))
    except ModbusException as e:
        print(json.dumps({"error": str(e)}))
    finally:
        client.close()


main()

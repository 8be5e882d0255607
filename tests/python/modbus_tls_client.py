#!/usr/bin/env python3
"""A third-party Modbus/TCP Security client (pymodbus's ModbusTlsClient)
for drivegate's tests.

Usage: modbus_tls_client.py HOST PORT CA CERT KEY STEP...

  CA          the PEM CA that signed the server's certificate
  CERT KEY    the client's PEM certificate and key, or - - for none
  STEP        read:UNIT:ADDRESS:COUNT (0x03), write:UNIT:ADDRESS:VALUE (0x06)

The steps run in order on one TLS connection. Prints one JSON object:
{"connected": false, "error": ...} when the connection or the handshake
fails, else {"connected": true, "results": [...]}, each result
{"registers": [...]}, {"written": true}, {"exception": n} or {"error": ...}
(no answer: the server closed the connection).
"""

import json
import ssl
import sys

try:
    from pymodbus.client import ModbusTlsClient
    from pymodbus.exceptions import ModbusException
except ImportError:
    print("pymodbus is not installed: install it with `pip install 'pymodbus>=3.10'`", file=sys.stderr)
    sys.exit(3)


def main():
    host, port, ca, cert, key, *steps = sys.argv[1:]
    ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=ca)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    # The chain is verified; the server certificate is for 127.0.0.1.
    ctx.check_hostname = False
    if cert != "-":
        ctx.load_cert_chain(cert, key)
    client = ModbusTlsClient(host, port=int(port), sslctx=ctx, timeout=3, retries=0)
    if not client.connect():
        print(json.dumps({"connected": False, "error": "cannot connect"}))
        return
    results = []
    try:
        for step in steps:
            op, unit, address, arg = step.split(":")
            unit, address, arg = int(unit, 0), int(address, 0), int(arg, 0)
            try:
                if op == "read":
                    rr = client.read_holding_registers(address, count=arg, device_id=unit)
                    ok = None if rr.isError() else {"registers": list(rr.registers)}
                else:
                    rr = client.write_register(address, arg, device_id=unit)
                    ok = None if rr.isError() else {"written": True}
                results.append(ok or {"exception": getattr(rr, "exception_code", None)})
            except (ModbusException, OSError) as e:
                results.append({"error": str(e)})
    finally:
        client.close()
    connected = not (results and all("error" in r for r in results))
    print(json.dumps({"connected": connected, "results": results}))


if __name__ == "__main__":
    main()

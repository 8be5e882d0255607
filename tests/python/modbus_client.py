#!/usr/bin/env python3
"""A third-party Modbus TCP client (pymodbus) for drivegate's tests.

Usage: modbus_client.py HOST PORT COMMAND ARGS...

  read UNIT ADDRESS COUNT          read holding registers (0x03)
  write UNIT ADDRESS VALUE         write single register (0x06)
  write-multiple UNIT ADDRESS V,.. write multiple registers (0x10)
  broadcast ADDRESS VALUE          write single register to unit 0, no reply
  calls UNIT NAME...               pymodbus's own request for each NAME (see
                                   CALLS: mask writes, read/write multiple,
                                   coils, files, diagnostics, device
                                   identification), one result per name
  swarm CLIENTS ROUNDS DRIVES      CLIENTS connections at once, each writing
                                   its own register on one of DRIVES drives,
                                   reading it back and reading the status
                                   block; every reply is checked against its
                                   request

Needs pymodbus 3.10 or later (`device_id=`). Addresses are the drive's own
(0xC0 = 192 is the status block). Numbers may be decimal or 0x-hex. Prints
one JSON object; exit status 0 unless the client itself failed (a Modbus
exception is a result, printed as {"exception": n}).
"""

import asyncio
import json
import sys

try:
    from pymodbus.client import AsyncModbusTcpClient, ModbusTcpClient
    from pymodbus.exceptions import ModbusException
    from pymodbus.pdu import FileRecord
except ImportError:
    print(
        "pymodbus is not installed: install it with `pip install 'pymodbus>=3.10'`",
        file=sys.stderr,
    )
    sys.exit(3)


def number(text):
    return int(text, 0)


def result(response, **fields):
    if response.isError():
        return {"exception": getattr(response, "exception_code", None)}
    return fields


# CONFIG (0x0002) = 6 is the factory reset; 0x0024 is INERTIA_RATIO.
CALLS = {
    "mask-write-reset": lambda c, u: c.mask_write_register(
        address=0x0002, and_mask=0x0000, or_mask=0x0006, device_id=u
    ),
    "mask-write-keeping-bits": lambda c, u: c.mask_write_register(
        address=0x0002, and_mask=0xFFF0, or_mask=0x0006, device_id=u
    ),
    "mask-write-inertia-9": lambda c, u: c.mask_write_register(
        address=0x0024, and_mask=0x0000, or_mask=9, device_id=u
    ),
    "read-write-reset": lambda c, u: c.readwrite_registers(
        read_address=0x00C0, read_count=7, write_address=0x0002, values=[6], device_id=u
    ),
    "read-write-inertia-5": lambda c, u: c.readwrite_registers(
        read_address=0x0024, read_count=1, write_address=0x0024, values=[5], device_id=u
    ),
    "write-coil": lambda c, u: c.write_coil(1, True, device_id=u),
    "write-coils": lambda c, u: c.write_coils(0, [True] * 10, device_id=u),
    "write-file-record": lambda c, u: c.write_file_record(
        [FileRecord(file_number=4, record_number=7, record_data=b"\x06\xaf")], device_id=u
    ),
    "diag-restart": lambda c, u: c.diag_restart_communication(False, device_id=u),
    "diag-listen-only": lambda c, u: c.diag_force_listen_only(
        device_id=u, no_response_expected=False
    ),
    "diag-clear-counters": lambda c, u: c.diag_clear_counters(device_id=u),
    "diag-bus-messages": lambda c, u: c.diag_read_bus_message_count(device_id=u),
    "read-coils": lambda c, u: c.read_coils(0, count=8, device_id=u),
    "read-input-registers": lambda c, u: c.read_input_registers(0xC0, count=7, device_id=u),
    "read-exception-status": lambda c, u: c.read_exception_status(device_id=u),
    "report-server-id": lambda c, u: c.report_device_id(device_id=u),
    "read-device-information": lambda c, u: c.read_device_information(device_id=u),
}


def outcome(call, client, unit):
    try:
        rr = call(client, unit)
    except (ModbusException, OSError) as e:
        return {"error": str(e)}
    if rr.isError():
        return {"exception": getattr(rr, "exception_code", None)}
    return {"ok": True, "registers": list(getattr(rr, "registers", []) or [])}


def single(host, port, command, args):
    client = ModbusTcpClient(host, port=port, timeout=3, retries=0)
    if not client.connect():
        return {"error": f"cannot connect to {host}:{port}"}
    try:
        if command == "read":
            unit, address, count = map(number, args)
            rr = client.read_holding_registers(address, count=count, device_id=unit)
            return result(rr, registers=None if rr.isError() else list(rr.registers))
        if command == "write":
            unit, address, value = map(number, args)
            rr = client.write_register(address, value, device_id=unit)
            return result(rr, written=True)
        if command == "write-multiple":
            unit, address = number(args[0]), number(args[1])
            values = [number(v) for v in args[2].split(",")]
            rr = client.write_registers(address, values, device_id=unit)
            return result(rr, written=True)
        if command == "calls":
            unit = number(args[0])
            return {name: outcome(CALLS[name], client, unit) for name in args[1:]}
        if command == "broadcast":
            address, value = map(number, args)
            client.write_register(address, value, device_id=0, no_response_expected=True)
            return {"sent": True}
        return {"error": f"unknown command {command}"}
    except (ModbusException, OSError) as e:
        # A server that refuses the connection closes it, reset when the
        # request was already in: either way, no answer.
        return {"error": str(e)}
    finally:
        client.close()


# Registers a swarm client may own: read/write, harmless while the motor
# stands still, accepting 1..60000 (STALLED_DURATION_MS, SPEED_TD_R_LOW,
# POSITION_TD_R_LOW, INERTIA_RATIO).
OWNED = [0x000E, 0x001A, 0x0020, 0x0024]


async def swarm_client(host, port, k, rounds, drives, mismatches):
    unit = k % drives + 1
    register = OWNED[(k // drives) % len(OWNED)]
    client = AsyncModbusTcpClient(host, port=port, timeout=10, retries=0)
    await client.connect()
    if not client.connected:
        mismatches.append(f"client {k}: cannot connect")
        return 0
    checked = 0
    try:
        for r in range(rounds):
            value = 1 + (k * 1000 + r * 7) % 60000
            w = await client.write_register(register, value, device_id=unit)
            if w.isError() or w.address != register or w.registers != [value]:
                mismatches.append(f"client {k} round {r}: write echo {w}")
            rr = await client.read_holding_registers(register, count=1, device_id=unit)
            if rr.isError() or rr.registers != [value]:
                mismatches.append(
                    f"client {k} round {r}: unit {unit} reg 0x{register:04X} wrote {value}, read {rr}"
                )
            count = 1 + (k + r) % 7
            st = await client.read_holding_registers(0xC0, count=count, device_id=unit)
            if st.isError() or len(st.registers) != count:
                mismatches.append(f"client {k} round {r}: status read of {count} got {st}")
            elif count >= 5 and st.registers[4] == 0:
                mismatches.append(f"client {k} round {r}: VOLT reads 0 in {st.registers}")
            checked += 3
    except ModbusException as e:
        mismatches.append(f"client {k}: {e}")
    finally:
        client.close()
    return checked


async def swarm(host, port, clients, rounds, drives):
    mismatches = []
    counts = await asyncio.gather(
        *(swarm_client(host, port, k, rounds, drives, mismatches) for k in range(clients))
    )
    return {"clients": clients, "checked": sum(counts), "mismatches": mismatches}


def main():
    if len(sys.argv) < 4:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    host, port, command, args = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4:]
    if command == "swarm":
        clients, rounds, drives = map(number, args)
        out = asyncio.run(swarm(host, port, clients, rounds, drives))
    else:
        out = single(host, port, command, args)
    print(json.dumps(out))
    sys.exit(1 if "error" in out else 0)


if __name__ == "__main__":
    main()

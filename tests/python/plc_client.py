#!/usr/bin/env python3
"""A PLC over Modbus TCP (pymodbus), driven line by line from a test.

Usage: plc_client.py HOST PORT

Reads commands on stdin, one per line, and answers each with one JSON line
on stdout:

  write UNIT ADDRESS VALUE   write single register (0x06)  {"written": true}
                                                           or {"exception": n}
  poll UNIT PERIOD_MS        from now on, read the status block's first
                             register every PERIOD_MS in the background,
                             as a PLC's cycle does          {"polling": true}
  silence                    stop sending anything; the socket stays open
                                                           {"silent": true,
                                                            "polls": n,
                                                            "failed": n}
  close                      close the socket (FIN)        {"closed": true}

A process killed with SIGKILL closes its socket too (the kernel sends the
FIN): a connection that dies without one needs a cut network between the
client and the daemon, which the test provides.

Needs pymodbus 3.10 or later (`device_id=`). Numbers may be decimal or
0x-hex. Exit status 3 when pymodbus is missing.
"""

import json
import sys
import threading

try:
    from pymodbus.client import ModbusTcpClient
    from pymodbus.exceptions import ModbusException
except ImportError:
    print(
        "pymodbus is not installed: install it with `pip install 'pymodbus>=3.10'`",
        file=sys.stderr,
    )
    sys.exit(3)


def number(text):
    return int(text, 0)


def say(obj):
    print(json.dumps(obj), flush=True)


class Plc:
    def __init__(self, host, port):
        self.client = ModbusTcpClient(host, port=port, timeout=5, retries=0)
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.poller = None
        self.polls = 0
        self.failed = 0

    def write(self, unit, address, value):
        with self.lock:
            rr = self.client.write_register(address, value, device_id=unit)
        if rr.isError():
            return {"exception": getattr(rr, "exception_code", None)}
        return {"written": True}

    def poll(self, unit, period_ms):
        def run():
            while not self.stop.wait(period_ms / 1000.0):
                try:
                    with self.lock:
                        if self.stop.is_set():
                            return
                        rr = self.client.read_holding_registers(0xC0, count=1, device_id=unit)
                    if rr.isError():
                        self.failed += 1
                    else:
                        self.polls += 1
                except ModbusException:
                    self.failed += 1

        self.poller = threading.Thread(target=run, daemon=True)
        self.poller.start()
        return {"polling": True}

    def silence(self):
        self.stop.set()
        if self.poller is not None:
            self.poller.join()
        return {"silent": True, "polls": self.polls, "failed": self.failed}

    def close(self):
        self.silence()
        self.client.close()
        return {"closed": True}


def main():
    if len(sys.argv) != 3:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    plc = Plc(sys.argv[1], int(sys.argv[2]))
    if not plc.client.connect():
        say({"error": f"cannot connect to {sys.argv[1]}:{sys.argv[2]}"})
        sys.exit(1)
    say({"connected": True})
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        command, args = words[0], words[1:]
        try:
            if command == "write":
                say(plc.write(*map(number, args)))
            elif command == "poll":
                say(plc.poll(*map(number, args)))
            elif command == "silence":
                say(plc.silence())
            elif command == "close":
                say(plc.close())
            else:
                say({"error": f"unknown command {command}"})
        except ModbusException as e:
            say({"error": str(e)})
    # stdin closed: stay silent with the socket open until killed.
    threading.Event().wait()


if __name__ == "__main__":
    main()

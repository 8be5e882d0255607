#!/usr/bin/env python3
"""Many OPC UA sessions from chosen local addresses (asyncua), as an
attacker or a crowd of HMIs would open them: one client, one connection and
one session each, on the None endpoint.

Usage: opcua_sessions.py URL GROUP...

Each GROUP is SOURCE,COUNT or SOURCE,COUNT,USER,PASSWORD: COUNT sessions,
each from the local address SOURCE (any 127.x.y.z on Linux), anonymous
unless a user is given. The groups are opened one after the other, each
session after the last, and each group answered with one JSON line:
{"source": ..., "opened": n, "refused": ["BadTooManySessions", ...],
"slowest_ms": ms}. The sessions are held open until the input closes (or
says "close"); then they are closed and {"closed": n} is printed.
"""

import asyncio
import json
import sys
import time

from asyncua import Client

ORIGINAL = asyncio.BaseEventLoop.create_connection
SOURCE = [None]


async def bound(self, *args, **kwargs):
    """Every connection of this process from the current group's address."""
    if SOURCE[0] is not None:
        kwargs.setdefault("local_addr", (SOURCE[0], 0))
    return await ORIGINAL(self, *args, **kwargs)


asyncio.BaseEventLoop.create_connection = bound


def say(obj):
    print(json.dumps(obj), flush=True)


def status_name(text):
    words = text.replace("(", " ").replace(")", " ").replace(":", " ").replace(",", " ").split()
    return next((w for w in words if w.startswith("Bad")), text)


async def group(url, spec, held):
    parts = spec.split(",")
    source, count = parts[0], int(parts[1])
    user = parts[2:4] if len(parts) >= 4 else None
    SOURCE[0] = source
    opened, refused, slowest = 0, [], 0.0
    for _ in range(count):
        c = Client(url, timeout=20)
        if user:
            c.set_user(user[0])
            c.set_password(user[1])
        started = time.monotonic()
        try:
            await c.connect()
            held.append(c)
            opened += 1
        except Exception as e:  # a refusal is a result
            refused.append(status_name(str(e)))
        slowest = max(slowest, (time.monotonic() - started) * 1000)
    say({"source": source, "opened": opened, "refused": refused, "slowest_ms": round(slowest, 1)})


async def main():
    if len(sys.argv) < 3:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    url, groups = sys.argv[1], sys.argv[2:]
    held = []
    for spec in groups:
        await group(url, spec, held)
    loop = asyncio.get_running_loop()
    while True:
        line = await loop.run_in_executor(None, sys.stdin.readline)
        if line.strip() in ("close", ""):
            break
    for c in held:
        try:
            await c.disconnect()
        except Exception:
            pass
    say({"closed": len(held)})


if __name__ == "__main__":
    asyncio.run(main())

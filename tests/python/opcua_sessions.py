#!/usr/bin/env python3
"""Many OPC UA sessions from one local address (asyncua), as an attacker
or a crowd of HMIs would open them: one client, one connection and one
session each, on the None endpoint.

Usage: opcua_sessions.py URL SOURCE COUNT [--user U --password P]

Every connection is made from the local address SOURCE (any 127.x.y.z on
Linux). Opens the COUNT sessions one after the other, anonymous unless a
user is given, and prints one JSON line:
{"opened": n, "refused": ["BadTooManySessions", ...], "slowest_ms": ms}.
Holds them open until its input closes (or says "close"), then closes them
and prints {"closed": n}.
"""

import argparse
import asyncio
import json
import sys
import time

from asyncua import Client

ORIGINAL = asyncio.BaseEventLoop.create_connection


def from_source(source):
    """Makes every connection of this process from `source`."""

    async def bound(self, *args, **kwargs):
        kwargs.setdefault("local_addr", (source, 0))
        return await ORIGINAL(self, *args, **kwargs)

    asyncio.BaseEventLoop.create_connection = bound


def say(obj):
    print(json.dumps(obj), flush=True)


async def main():
    p = argparse.ArgumentParser()
    p.add_argument("url")
    p.add_argument("source")
    p.add_argument("count", type=int)
    p.add_argument("--user")
    p.add_argument("--password")
    args = p.parse_args()
    from_source(args.source)
    opened, refused, slowest = [], [], 0.0
    for _ in range(args.count):
        c = Client(args.url, timeout=20)
        if args.user:
            c.set_user(args.user)
            c.set_password(args.password)
        started = time.monotonic()
        try:
            await c.connect()
            opened.append(c)
        except Exception as e:  # a refusal is a result
            text = str(e)
            name = next((w for w in text.replace("(", " ").replace(")", " ").replace(":", " ").replace(",", " ").split() if w.startswith("Bad")), text)
            refused.append(name)
        slowest = max(slowest, (time.monotonic() - started) * 1000)
    say({"opened": len(opened), "refused": refused, "slowest_ms": round(slowest, 1)})
    loop = asyncio.get_running_loop()
    while True:
        line = await loop.run_in_executor(None, sys.stdin.readline)
        if line.strip() in ("close", ""):
            break
    for c in opened:
        try:
            await c.disconnect()
        except Exception:
            pass
    say({"closed": len(opened)})


if __name__ == "__main__":
    asyncio.run(main())

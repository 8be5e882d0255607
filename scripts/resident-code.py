#!/usr/bin/env python3
"""Which of a running drivegate's code is resident, by crate.

    scripts/resident-code.py PID [BINARY]

Reads /proc/PID/pagemap (root, or the daemon's own user) for every page of
the binary's mappings, keeps those present, and gives each present page of
code to the symbols it holds (`nm -S -C` of BINARY, by default the file
/proc/PID/exe points to), summed by the crate that starts each symbol's
name. Generic code is named after the crate that defines it (`core`,
`alloc`), wherever it was instantiated.

The kernel maps a file's pages 64 KiB at a time around each fault
(fault-around), so a resident page is not always a page that ran: what it
shows is what a part of the code costs in resident memory, which is what
`RssFile` counts.
"""

import bisect
import collections
import os
import re
import struct
import subprocess
import sys

PAGE = os.sysconf("SC_PAGE_SIZE")


def mappings(pid, binary):
    """The (start, end, perms, file offset) of each mapping of `binary`."""
    out = []
    with open(f"/proc/{pid}/maps") as maps:
        for line in maps:
            parts = line.split()
            if len(parts) >= 6 and parts[5] == binary:
                start, end = (int(x, 16) for x in parts[0].split("-"))
                out.append((start, end, parts[1], int(parts[2], 16)))
    return out


def present_pages(pid, maps):
    """The file offset and perms of each present page of `maps`."""
    pages = []
    with open(f"/proc/{pid}/pagemap", "rb") as pagemap:
        for start, end, perms, offset in maps:
            for address in range(start, end, PAGE):
                pagemap.seek(address // PAGE * 8)
                (entry,) = struct.unpack("<Q", pagemap.read(8))
                if entry >> 63 & 1:
                    pages.append((offset + address - start, perms))
    return pages


def segments(binary):
    """The LOAD segments: (file offset, virtual address, file size)."""
    text = subprocess.run(
        ["readelf", "-lW", binary], capture_output=True, text=True, check=True
    ).stdout
    out = []
    for line in text.splitlines():
        m = re.match(
            r"\s*LOAD\s+(0x[0-9a-f]+)\s+(0x[0-9a-f]+)\s+\S+\s+(0x[0-9a-f]+)", line
        )
        if m:
            out.append(tuple(int(x, 16) for x in m.groups()))
    return out


def symbols(binary):
    """The code's symbols: (address, size, demangled name), by address."""
    text = subprocess.run(
        ["nm", "-S", "--defined-only", "-C", binary],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    out = []
    for line in text.splitlines():
        parts = line.split(" ", 3)
        if len(parts) == 4 and parts[2] in "tTwW":
            try:
                out.append((int(parts[0], 16), int(parts[1], 16), parts[3]))
            except ValueError:
                pass
    out.sort()
    return out


def crate(name):
    """The crate a symbol's name starts with; for an implementation on a
    type parameter (`<F as core::future::Future>::poll`), the trait's."""
    name = re.sub(r"^<+(impl |dyn |&mut |&)?", "", name)
    m = re.match(r"([A-Z][A-Za-z0-9]?) as <*([a-z_][a-z0-9_]*)::", name)
    if m:
        return m.group(2)
    m = re.match(r"[A-Za-z_][A-Za-z0-9_]*", name)
    return m.group(0) if m else "(other)"


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    pid = int(sys.argv[1])
    binary = sys.argv[2] if len(sys.argv) > 2 else os.readlink(f"/proc/{pid}/exe")
    maps = mappings(pid, binary)
    if not maps:
        sys.exit(f"process {pid} maps nothing of {binary}")
    pages = present_pages(pid, maps)
    by_perms = collections.Counter(perms for _, perms in pages)
    for perms, count in sorted(by_perms.items()):
        print(f"{perms}: {count * PAGE / 2**20:.1f} MiB resident")

    segs = segments(binary)
    syms = symbols(binary)
    starts = [s[0] for s in syms]
    longest = max((s[1] for s in syms), default=0)
    by_crate = collections.Counter()
    unnamed = 0
    for offset, perms in pages:
        if "x" not in perms:
            continue
        address = next(
            (va + offset - o for o, va, size in segs if o <= offset < o + size), None
        )
        if address is None:
            unnamed += PAGE
            continue
        covered = 0
        i = bisect.bisect_right(starts, address + PAGE) - 1
        # Symbols that start before the page may reach into it.
        while i >= 0 and syms[i][0] + longest > address:
            start, size, name = syms[i]
            overlap = min(start + size, address + PAGE) - max(start, address)
            if overlap > 0:
                by_crate[crate(name)] += overlap
                covered += overlap
            i -= 1
        unnamed += max(0, PAGE - covered)
    print("resident code by crate, KiB:")
    for name, size in by_crate.most_common(30):
        print(f"{size / 1024:8.0f}  {name}")
    print(f"{unnamed / 1024:8.0f}  (no symbol)")


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""A paced RTU simulator of status-reading drives, outside drivegate.

It serves drives on one end of a socat pty pair and prints the other end's
path (the link) on stdout once a master can open it. Each reply byte is
written at its wire time (115200 8N1 by default: 86.8 us a byte), so what a
master loses between the wire and itself shows: a simulator inside the
master's own process hides the delivery delays of a real second program.

Per drive, the silence after which it parts frames (`--frame-gap-us`, the
spec's 1750 us by default; `--strict-units` keep the spec's): a request
that follows the previous frame sooner is, for that drive, one garbled frame
with the previous one, and it does not answer. A drive answers `turnaround`
after its own frame gap. Faults: `--drop-rate`, `--crc-error-rate`, seeded.

SIGUSR1 starts a new window of counters; SIGTERM prints the window's
counters on one line (requests, replies, merged, gap quantiles) and exits.
"""

import argparse, os, random, select, signal, subprocess, sys, termios, time, tty

def crc16(data):
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return bytes([crc & 0xFF, crc >> 8])

def units(text):
    out = set()
    for part in filter(None, (p.strip() for p in text.split(","))):
        low, _, high = part.partition("-")
        out.update(range(int(low), int(high or low) + 1))
    return out

def request_length(buf):
    """Bytes of the request in `buf`, or None while unknown."""
    if len(buf) < 2:
        return None
    if buf[1] in (3, 4, 6):
        return 8
    if buf[1] == 16:
        return 9 + buf[6] if len(buf) >= 7 else None
    return None

def answer(pdu):
    fc = pdu[0]
    if fc == 3:
        addr, count = int.from_bytes(pdu[1:3], "big"), int.from_bytes(pdu[3:5], "big")
        if addr == 0xC0 and count == 7:   # status: active, calibrated, speed mode
            regs = [0, 1234, 0, 0, 24, 30, 0xC8]
        else:
            regs = [0] * count
        return bytes([3, 2 * count]) + b"".join(r.to_bytes(2, "big") for r in regs)
    if fc == 6:
        return pdu[:5]
    if fc == 16:
        return pdu[:5]
    return bytes([fc | 0x80, 1])

def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--link", required=True)
    p.add_argument("--units", default="1-8", type=units)
    p.add_argument("--baud", type=int, default=115200)
    p.add_argument("--turnaround-ms", type=float, default=0.5)
    p.add_argument("--frame-gap-us", type=float, default=None)
    p.add_argument("--strict-units", default="", type=units)
    p.add_argument("--drop-rate", type=float, default=0.0)
    p.add_argument("--crc-error-rate", type=float, default=0.0)
    p.add_argument("--seed", type=int, default=1)
    a = p.parse_args()
    char = 10.0 / a.baud
    t35 = 0.00175 if a.baud > 19200 else 3.5 * char
    gap = {u: t35 if (u in a.strict_units or a.frame_gap_us is None) else a.frame_gap_us / 1e6
           for u in a.units}
    rng = random.Random(a.seed)
    far = a.link + ".sim"
    socat = subprocess.Popen(["socat", f"pty,raw,echo=0,link={a.link}",
                              f"pty,raw,echo=0,link={far}"], stderr=subprocess.DEVNULL)
    while not (os.path.exists(a.link) and os.path.exists(far)):
        time.sleep(0.01)
    fd = os.open(far, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(fd)
    print(a.link, flush=True)

    counts = {}
    gaps = []
    def reset(*_):
        counts.clear(); gaps.clear()
        counts.update(requests=0, replies=0, merged=0, violations=0, dropped=0, corrupted=0)
    def finish(*_):
        gaps.sort()
        q = lambda f: round(gaps[min(len(gaps) - 1, int(f * len(gaps)))] * 1e6) if gaps else 0
        print(" ".join(f"{k}={v}" for k, v in counts.items()),
              f"gap_p50_us={q(0.5)} gap_p99_us={q(0.99)}", flush=True)
        socat.kill()
        socat.wait()
        os._exit(0)
    reset()
    signal.signal(signal.SIGUSR1, reset)
    signal.signal(signal.SIGTERM, finish)
    signal.signal(signal.SIGINT, finish)

    def wait_until(t):
        left = t - time.perf_counter()
        if left > 0.0004:
            time.sleep(left - 0.0003)
        while time.perf_counter() < t:
            pass

    buf, first, quiet_from = b"", None, None
    while True:
        timeout = None if not buf else max(0.0, first + char * len(buf) + t35 - time.perf_counter())
        try:
            ready, _, _ = select.select([fd], [], [], timeout)
        except InterruptedError:
            continue
        now = time.perf_counter()
        if not ready:                      # a partial frame ended by silence
            buf = b""
            continue
        try:
            chunk = os.read(fd, 512)
        except BlockingIOError:
            continue
        if not buf:
            first = now
        buf += chunk
        n = request_length(buf)
        if n is None or len(buf) < n:
            if len(buf) > 256:
                buf = b""
            continue
        frame, buf = buf[:n], buf[n:]
        arrival = first
        first = now
        # The silence the drives heard before this frame.
        silence = 1.0 if quiet_from is None else arrival - quiet_from
        start = arrival if quiet_from is None else max(arrival, quiet_from)
        wire_end = start + char * n
        quiet_from = wire_end
        if frame[-2:] != crc16(frame[:-2]):
            continue
        counts["requests"] += 1
        unit = frame[0]
        if silence < 1.0:
            gaps.append(max(0.0, silence))
        if silence < t35:
            counts["violations"] += 1
        if unit not in gap:
            continue
        if silence < gap[unit]:            # one garbled frame with the last
            counts["merged"] += 1
            continue
        if rng.random() < a.drop_rate:
            counts["dropped"] += 1
            continue
        reply = bytes([unit]) + answer(frame[1:-2])
        reply += crc16(reply)
        if rng.random() < a.crc_error_rate:
            reply = reply[:-1] + bytes([reply[-1] ^ 0x01])
            counts["corrupted"] += 1
        begin = wire_end + gap[unit] + a.turnaround_ms / 1e3
        for i in range(len(reply)):
            wait_until(begin + char * (i + 1))
            os.write(fd, reply[i:i + 1])
        quiet_from = begin + char * len(reply)
        counts["replies"] += 1

if __name__ == "__main__":
    main()

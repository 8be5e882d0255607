#!/usr/bin/env python3
"""Builds the tests with `cargo test --locked --no-run` and runs the test
binaries side by side, the longest first.

Most tests wait on the simulated wire and on timers, not on the CPU, so one
binary after another (what `cargo test` does) leaves the machine idle most of
the time. Each binary's output goes to target/test-logs/NAME.log and is
printed whole when the binary fails. How long each binary took is kept in
target/test-logs/durations.tsv to order the next run; before a first run,
tests/durations.tsv (seconds measured once, only an order) stands in.

Usage: run-tests.py [--jobs N]   (scripts/test calls it with no arguments)
"""

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LOGS = ROOT / "target" / "test-logs"
DURATIONS = LOGS / "durations.tsv"
FIRST_ORDER = ROOT / "tests" / "durations.tsv"


def say(message):
    print(f"scripts/test: {message}", file=sys.stderr, flush=True)


def build():
    """Builds every test target; returns [(name, argv)] to run."""
    command = [
        "cargo", "test", "--locked", "--no-run",
        "--message-format=json-render-diagnostics",
    ]
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, text=True)
    runs = []
    for line in process.stdout:
        try:
            message = json.loads(line)
        except json.JSONDecodeError:
            continue
        if message.get("reason") != "compiler-artifact":
            continue
        executable = message.get("executable")
        if not executable or not message.get("profile", {}).get("test"):
            continue
        target = message["target"]
        kind = target["kind"][0]
        name = target["name"] if kind in ("test", "bench") else f"{kind}:{target['name']}"
        runs.append((name, [executable]))
    if process.wait() != 0:
        say("the tests do not build (errors above)")
        sys.exit(process.returncode or 1)
    # The documentation's examples, which only cargo can run.
    runs.append(("doc", ["cargo", "test", "--locked", "--doc", "--quiet"]))
    return runs


def read_durations(path):
    durations = {}
    try:
        for line in path.read_text().splitlines():
            name, _, seconds = line.partition("\t")
            durations[name] = float(seconds)
    except (OSError, ValueError):
        pass
    return durations


def known_durations():
    return read_durations(FIRST_ORDER) | read_durations(DURATIONS)


def summary_line(log_text):
    """The last `test result:` line of a binary's output."""
    lines = [l for l in log_text.splitlines() if l.startswith("test result:")]
    return lines[-1] if lines else "(no test result line)"


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument(
        "--jobs",
        type=int,
        default=int(os.environ.get("DRIVEGATE_TEST_JOBS", "4")),
        help="test binaries at once (default 4, or DRIVEGATE_TEST_JOBS)",
    )
    jobs = max(1, parser.parse_args().jobs)

    runs = build()
    LOGS.mkdir(parents=True, exist_ok=True)
    durations = known_durations()
    # Longest first; a binary never timed before counts as long.
    runs.sort(key=lambda run: -durations.get(run[0], 1e9))

    env = dict(os.environ, CARGO_MANIFEST_DIR=str(ROOT))
    waiting = list(runs)
    running = {}
    finished = []
    started = time.monotonic()
    say(f"running {len(runs)} test binaries, {jobs} at a time")
    while waiting or running:
        while waiting and len(running) < jobs:
            name, argv = waiting.pop(0)
            log = open(LOGS / f"{name.replace(':', '-')}.log", "w")
            process = subprocess.Popen(
                argv, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT
            )
            running[process.pid] = (name, process, log, time.monotonic())
        pid, status = os.wait()
        if pid not in running:
            continue
        name, process, log, began = running.pop(pid)
        process.returncode = os.waitstatus_to_exitcode(status)
        log.close()
        seconds = time.monotonic() - began
        text = Path(log.name).read_text(errors="replace")
        ok = process.returncode == 0
        finished.append((name, ok, seconds))
        if ok:
            say(f"{name}: {summary_line(text)} ({seconds:.1f} s)")
        else:
            print(text, flush=True)
            say(f"{name}: FAILED, exit {process.returncode} ({seconds:.1f} s); log: {log.name}")

    durations.update({name: seconds for name, ok, seconds in finished if ok})
    DURATIONS.write_text("".join(f"{n}\t{s:.1f}\n" for n, s in sorted(durations.items())))

    failed = [name for name, ok, _ in finished if not ok]
    total = time.monotonic() - started
    if failed:
        say(f"FAILED: {', '.join(failed)} ({total:.0f} s); logs in {LOGS}")
        sys.exit(1)
    say(f"all {len(finished)} test binaries passed in {total:.0f} s")


if __name__ == "__main__":
    main()

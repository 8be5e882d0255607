#!/usr/bin/env python3
"""Builds the tests with `cargo test --locked --no-run` and runs them, each
end-to-end test in a process of its own, several at once, the longest first.

Most tests wait on the simulated wire and on timers, not on the CPU, so the
tests of a binary in the threads of one process (what `cargo test` does) leave
the machine idle most of the time, and the slowest tests hold up the rest.
Here every end-to-end test (tests/main.rs, a module per area) is run as
`BINARY --exact NAME`, and a pool keeps `--jobs` of them going; the unit tests
(a fraction of a second) run as one process. A test is shown by its area:
`api::leases::name` as `api/leases::name`. A failed test's whole output is printed; every test's is kept under
target/test-logs/. How long each took is kept in target/test-logs/durations.tsv
to order the next run; before a first run, tests/durations.tsv (seconds
measured once, only an order) stands in.

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
# Seconds after which a test process is killed and counted as failed.
LIMIT = 600


def say(message):
    print(f"scripts/test: {message}", file=sys.stderr, flush=True)


def build():
    """Builds every test target; returns [(binary name, executable, split)]
    where `split` says to run its tests one process each."""
    command = [
        "cargo", "test", "--locked", "--no-run",
        "--message-format=json-render-diagnostics",
    ]
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, text=True)
    binaries = []
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
        if kind == "test":
            binaries.append((target["name"], executable, True))
        else:
            binaries.append((f"{kind}:{target['name']}", executable, False))
    if process.wait() != 0:
        say("the tests do not build (errors above)")
        sys.exit(process.returncode or 1)
    return binaries


def listed(executable, ignored=False):
    argv = [executable, "--list", "--format", "terse"] + (["--ignored"] if ignored else [])
    out = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, check=True).stdout
    return [l[: -len(": test")] for l in out.splitlines() if l.endswith(": test")]


def key_of(binary, test):
    """`api/leases::name` for the test `api::leases::name`: its area first."""
    area, _, rest = test.partition("::")
    return f"{area}/{rest}" if rest else f"{binary}/{test}"


def jobs_of(binaries):
    """[(key, argv)]: one per end-to-end test, one per other binary."""
    jobs = []
    for name, executable, split in binaries:
        if not split:
            jobs.append((name, [executable]))
            continue
        ignored = set(listed(executable, ignored=True))
        for test in listed(executable):
            if test not in ignored:
                jobs.append((key_of(name, test), [executable, "--exact", test]))
    return jobs


def read_durations(path):
    durations = {}
    try:
        for line in path.read_text().splitlines():
            if line.startswith("#"):
                continue
            key, _, seconds = line.partition("\t")
            durations[key] = float(seconds)
    except (OSError, ValueError):
        pass
    return durations


def result_line(text):
    lines = [l for l in text.splitlines() if l.startswith("test result:")]
    return lines[-1] if lines else ""


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument(
        "--jobs",
        type=int,
        default=int(os.environ.get("DRIVEGATE_TEST_JOBS", "8")),
        help="tests at once (default 8, or DRIVEGATE_TEST_JOBS)",
    )
    jobs_at_once = max(1, parser.parse_args().jobs)

    binaries = build()
    LOGS.mkdir(parents=True, exist_ok=True)
    durations = read_durations(FIRST_ORDER) | read_durations(DURATIONS)
    waiting = jobs_of(binaries)
    # Longest first; a test never timed before counts as long.
    waiting.sort(key=lambda job: -durations.get(job[0], 1e9))

    # A test's own threads: it runs one test, with the tokio runtime its
    # attribute asks for.
    env = dict(os.environ, CARGO_MANIFEST_DIR=str(ROOT), RUST_TEST_THREADS="1")
    running = {}
    finished = []
    cpu = {}
    started = time.monotonic()
    say(f"running {len(waiting)} test processes from {len(binaries)} binaries, "
        f"{jobs_at_once} at a time")
    while waiting or running:
        while waiting and len(running) < jobs_at_once:
            key, argv = waiting.pop(0)
            path = LOGS / (key.replace("/", "--").replace(":", "-") + ".log")
            log = open(path, "w")
            process = subprocess.Popen(
                argv, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT
            )
            running[process.pid] = (key, process, log, time.monotonic())
        pid, status, usage = os.wait4(-1, os.WNOHANG)
        if pid == 0:
            # Every test bounds its own time; this is for one that does not.
            now = time.monotonic()
            for key, process, log, began in running.values():
                if now - began > LIMIT and process.returncode is None:
                    say(f"{key} still runs after {LIMIT} s: stopping it")
                    process.kill()
            time.sleep(0.02)
            continue
        if pid not in running:
            continue
        key, process, log, began = running.pop(pid)
        process.returncode = os.waitstatus_to_exitcode(status)
        log.close()
        seconds = time.monotonic() - began
        ok = process.returncode == 0
        # CPU of the test and of what it started and waited for (daemons,
        # clients, the browser): what the machine's cores paid for it.
        cpu[key] = usage.ru_utime + usage.ru_stime
        finished.append((key, ok, seconds))
        text = Path(log.name).read_text(errors="replace")
        if not ok:
            print(text, flush=True)
            say(f"FAILED {key} (exit {process.returncode}, {seconds:.1f} s); log: {log.name}")
        elif "/" not in key:
            say(f"{key}: {result_line(text)}")

    # The tests of this build only: a removed test's time goes with it.
    durations.update({key: seconds for key, ok, seconds in finished if ok})
    keep = {key for key, _, _ in finished}
    DURATIONS.write_text(
        "".join(f"{k}\t{s:.1f}\n" for k, s in sorted(durations.items()) if k in keep)
    )

    total = time.monotonic() - started
    failed = [key for key, ok, _ in finished if not ok]
    per_area = {}
    for key, ok, seconds in finished:
        area = key.split("/")[0]
        count, busy, used = per_area.get(area, (0, 0.0, 0.0))
        per_area[area] = (count + 1, busy + seconds, used + cpu.get(key, 0.0))
    for area, (count, busy, used) in sorted(per_area.items()):
        if count > 1:
            say(f"{area}: {count} tests, {busy:.0f} s of test time, {used:.0f} s of CPU")
    slowest = sorted(finished, key=lambda f: -f[2])[:3]
    say("slowest: " + ", ".join(f"{k} {s:.1f} s" for k, _, s in slowest))
    costliest = sorted(cpu.items(), key=lambda kv: -kv[1])[:5]
    say("most CPU: " + ", ".join(f"{k} {s:.1f} s" for k, s in costliest))
    (LOGS / "cpu.tsv").write_text(
        "".join(f"{k}\t{s:.2f}\n" for k, s in sorted(cpu.items()))
    )
    if failed:
        say(f"FAILED {len(failed)} of {len(finished)}: {', '.join(failed)} ({total:.0f} s); "
            f"logs in {LOGS}")
        sys.exit(1)
    say(f"all {len(finished)} passed in {total:.0f} s")


if __name__ == "__main__":
    main()

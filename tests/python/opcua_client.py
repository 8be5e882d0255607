"""An OPC UA client on asyncua (PyPI), the third-party client of the OPC UA
tests (tests/control/opcua.rs): one scenario per run, or several
(comma-separated) one after the other,

    python3 opcua_client.py URL SCENARIO[,SCENARIO...] [--drive D] [--user U --password P]
        [--policy none|basic256sha256|aes128|aes256 --cert C.der --key K.pem]
        [--user-cert C.der --user-key K.pem] [--source 127.0.0.2]

Prints one JSON object per line (`{"step": ..., ...}`) for the test to
check, and `{"step": "error", ...}` with exit status 1 when the server
answered otherwise than the scenario needs; the test decides what is right.
"""

import argparse
import asyncio
import json
import os
import sys
import time
import urllib.request
from datetime import datetime, timedelta, timezone

from asyncua import Client, ua
from asyncua.common.events import get_filter_from_event_type
from asyncua.crypto import security_policies as sp

NS = "urn:drivegate:drives"
POLICIES = {
    "none": None,
    "basic256sha256": sp.SecurityPolicyBasic256Sha256,
    "aes128": sp.SecurityPolicyAes128Sha256RsaOaep,
    "aes256": sp.SecurityPolicyAes256Sha256RsaPss,
}


def polls(metrics):
    """Status polls made on every bus so far, from the daemon's /metrics."""
    with urllib.request.urlopen(metrics, timeout=10) as r:
        text = r.read().decode()
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
               if line.startswith("drivegate_bus_polls_total{"))


def say(step, **fields):
    print(json.dumps({"step": step, **fields}, default=str), flush=True)


def fail(what, **fields):
    say("error", what=what, **fields)
    sys.exit(1)


def from_source(source):
    """Connections made from now on leave from `source` (a loopback
    address of its own: the server sees another client address)."""
    loop = asyncio.get_running_loop()
    plain = getattr(loop, "_plain_create_connection", None) or loop.create_connection
    loop._plain_create_connection = plain

    async def create_connection(*a, **kw):
        if source:
            kw.setdefault("local_addr", (source, 0))
        return await plain(*a, **kw)

    loop.create_connection = create_connection


async def client(args, timeout_ms=None):
    from_source(args.source)
    c = Client(args.url, timeout=20)
    if timeout_ms:
        c.session_timeout = timeout_ms
    if args.policy != "none":
        await c.set_security(
            POLICIES[args.policy],
            args.cert,
            args.key,
            mode=ua.MessageSecurityMode.SignAndEncrypt,
        )
    if args.user:
        c.set_user(args.user)
        c.set_password(args.password)
    if args.user_cert:
        await c.load_client_certificate(args.user_cert)
        await c.load_private_key(args.user_key)
    return c


def local_address(c):
    """The client's end of its connection, as the server sees it."""
    host, port = c.uaclient.protocol.transport.get_extra_info("sockname")[:2]
    return f"{host}:{port}"


async def node(c, name):
    ns = await c.get_namespace_index(NS)
    return c.get_node(ua.NodeId(f"Drives/{name}", ns))


async def call(c, drive, method, *inputs):
    d = await node(c, drive)
    m = await node(c, f"{drive}/{method}")
    return await d.call_method(m, *inputs)


def status_name(e):
    return type(e).__name__


async def endpoints(args):
    c = Client(args.url, timeout=20)
    eps = await c.connect_and_get_server_endpoints()
    say(
        "endpoints",
        endpoints=[
            {
                "url": e.EndpointUrl,
                "policy": e.SecurityPolicyUri.split("#")[-1],
                "mode": e.SecurityMode.name,
                "tokens": sorted({t.TokenType.name for t in e.UserIdentityTokens}),
            }
            for e in eps
        ],
    )


async def browse(args):
    async with await client(args) as c:
        ns = await c.get_namespace_index(NS)
        drives = await c.nodes.objects.get_child(f"{ns}:Drives")
        names = [(await n.read_browse_name()).Name for n in await drives.get_children()]
        d = await drives.get_child(f"{ns}:{args.drive}")
        kind = (await c.get_node(await d.read_type_definition()).read_browse_name()).Name
        children = sorted([(await n.read_browse_name()).Name for n in await d.get_children()])
        buses = await c.nodes.objects.get_child(f"{ns}:Buses")
        bus_names = [(await n.read_browse_name()).Name for n in await buses.get_children()]
        say("browse", drives=sorted(names), type=kind, children=children, buses=sorted(bus_names))


async def read(args):
    async with await client(args) as c:
        ns = await c.get_namespace_index(NS)
        out = {}
        for name in ["Speed", "Angle", "Turns", "Current", "Voltage", "Temperature", "Active", "Mode", "FaultCode", "Online"]:
            n = await node(c, f"{args.drive}/{name}")
            dv = await n.read_data_value(raise_on_bad_status=False)
            entry = {
                "value": dv.Value.Value if dv.Value is not None else None,
                "status": dv.StatusCode.name,
                "source_timestamp": dv.SourceTimestamp,
                "type": (await n.read_data_type_as_variant_type()).name,
            }
            try:
                eu = await (await n.get_child("0:EngineeringUnits")).read_value()
                rng = await (await n.get_child("0:EURange")).read_value()
                entry.update(unit=eu.DisplayName.Text, unit_id=eu.UnitId, low=rng.Low, high=rng.High)
            except ua.UaError:
                pass
            out[name] = entry
        msi = await (await node(c, f"{args.drive}/Speed")).read_attribute(ua.AttributeIds.MinimumSamplingInterval)
        # Each bus's variables (Objects/Buses/<bus>/*): value and status.
        buses = {}
        for b in await (await c.nodes.objects.get_child(f"{ns}:Buses")).get_children():
            values = {}
            for v in await b.get_children():
                dv = await v.read_data_value(raise_on_bad_status=False)
                values[(await v.read_browse_name()).Name] = {
                    "value": dv.Value.Value if dv.Value is not None else None,
                    "status": dv.StatusCode.name,
                }
            buses[(await b.read_browse_name()).Name] = values
        say("read", values=out, min_sampling_ms=msi.Value.Value, buses=buses)


async def described(args):
    """Every node under the drive (its variables, methods, Settings and the
    properties of each, recursively) with its Description, the drive's
    children in browse order, Mode's data type with its EnumStrings, and
    SetMode's argument."""
    async with await client(args) as c:
        d = await node(c, args.drive)
        order = [(await n.read_browse_name()).Name for n in await d.get_children()]
        missing, seen = [], 0
        stack = [(args.drive, d)]
        while stack:
            path, n = stack.pop()
            for child in await n.get_children(refs=ua.ObjectIds.HierarchicalReferences):
                name = f"{path}/{(await child.read_browse_name()).Name}"
                seen += 1
                try:
                    text = (await child.read_description()).Text
                except ua.UaStatusCodeError as e:
                    text = None
                    missing.append(f"{name}: {status_name(e)}")
                if text is not None and not text:
                    missing.append(f"{name}: empty")
                stack.append((name, child))
        mode = await node(c, f"{args.drive}/Mode")
        data_type = c.get_node(await mode.read_data_type())
        dt_name = (await data_type.read_browse_name()).Name
        dt_description = (await data_type.read_description()).Text
        strings = [t.Text for t in await (await data_type.get_child("0:EnumStrings")).read_value()]
        value = await mode.read_value()
        set_mode = await node(c, f"{args.drive}/SetMode")
        arg = (await (await set_mode.get_child("0:InputArguments")).read_value())[0]
        say("described", order=order, nodes=seen, missing=missing, mode_type=dt_name,
            mode_type_description=dt_description, enum_strings=strings, mode_value=value,
            argument={"name": arg.Name, "description": arg.Description.Text})


class Handler:
    def __init__(self, quiet=False):
        self.values = []
        self.events = []
        self.quiet = quiet

    def datachange_notification(self, n, val, data):
        dv = data.monitored_item.Value
        self.values.append((time.monotonic(), val, dv.StatusCode.name))
        if not self.quiet:
            say("value", value=val, status=dv.StatusCode.name, source_timestamp=dv.SourceTimestamp)

    def event_notification(self, event):
        self.events.append(event)


async def write(c, drive, name, value):
    n = await node(c, f"{drive}/{name}")
    try:
        await n.write_value(ua.DataValue(ua.Variant(value, ua.VariantType.Double)))
        return "Good"
    except ua.UaStatusCodeError as e:
        return status_name(e)


async def anonymous_write(args):
    async with await client(args) as c:
        got = await write(c, args.drive, "SpeedSetpoint", 100.0)
        level = await (await node(c, f"{args.drive}/SpeedSetpoint")).read_attribute(ua.AttributeIds.UserAccessLevel)
        say("anonymous-write", status=got, user_access_level=level.Value.Value)


async def operate(args):
    """An anonymous SpeedSetpoint write (refused), then as --user:
    SetMode("speed"), Activate(), SpeedSetpoint = --value, with a
    subscription to Speed that sees the motor turn; the Angle's
    notifications over 2 s at its minimum sampling interval, beside the
    polls of /metrics (--metrics), and through deadband filters; then
    an out-of-range setpoint with its diagnostics, SetMode("fast"), and
    Brake(). Each
    session says its client's address."""
    async with Client(args.url, timeout=20) as anonymous:
        got = await write(anonymous, args.drive, "SpeedSetpoint", 100.0)
        say("anonymous-write", status=got, address=local_address(anonymous))
    async with await client(args) as c:
        say("connected", address=local_address(c))
        h = Handler(quiet=True)
        sub = await c.create_subscription(50, h)
        speed = await node(c, f"{args.drive}/Speed")
        await sub.subscribe_data_change(speed, sampling_interval=0, queuesize=10)
        for method, inputs in [("SetMode", [ua.Variant("speed", ua.VariantType.String)]), ("Activate", [])]:
            try:
                await call(c, args.drive, method, *inputs)
            except ua.UaStatusCodeError as e:
                fail(method, status=status_name(e))
            say("called", method=method)
        got = await write(c, args.drive, "SpeedSetpoint", args.value)
        say("written", status=got)
        if got != "Good":
            sys.exit(1)
        t0 = time.monotonic()
        while time.monotonic() - t0 < args.seconds:
            if h.values and abs(h.values[-1][1] - args.value) < 1:
                break
            await asyncio.sleep(0.05)
        say("turned", reached=h.values[-1][1] if h.values else None)
        # The angle changes at every poll while the motor turns: monitored
        # at the sampling interval it says is its minimum (the poll's
        # period), in a subscription publishing as often, with a queue of
        # one (what most SCADA ask), its notifications come at the poll
        # rate; counted over the window below, beside the bus's polls.
        angle_node = await node(c, f"{args.drive}/Angle")
        msi = (await angle_node.read_attribute(ua.AttributeIds.MinimumSamplingInterval)).Value.Value
        angle = Handler(quiet=True)
        sub2 = await c.create_subscription(msi, angle)
        await sub2.subscribe_data_change(angle_node, sampling_interval=msi, queuesize=1)
        # Beside it, deadband filters (DataChangeFilter) on the same angle:
        # absolute (degrees) and percent (of its EURange, 360 degrees), one
        # narrower than a poll's step and one no change can exceed.
        deadbands = {}
        for name, value, kind in [("absolute-narrow", 0.01, 1), ("absolute-wide", 1000.0, 1),
                                  ("percent-narrow", 0.01, 2), ("percent-wide", 100.0, 2)]:
            hd = Handler(quiet=True)
            sd = await c.create_subscription(50, hd)
            await sd.deadband_monitor(angle_node, value, kind, queuesize=10)
            deadbands[name] = (sd, hd)
        # The window starts once the first values are in.
        await asyncio.sleep(0.3)
        angle.values.clear()
        polls0, t0 = polls(args.metrics), time.monotonic()
        await asyncio.sleep(2.0)
        n, polls1, window = len(angle.values), polls(args.metrics), time.monotonic() - t0
        await sub2.delete()
        for sd, _ in deadbands.values():
            await sd.delete()
        ts = [v[0] for v in angle.values]
        gaps = [round((b - a) * 1000) for a, b in zip(ts, ts[1:])]
        say("angle", notifications=n, window_s=window, polls=polls1 - polls0,
            sampling_ms=msi, publishing_ms=sub2.parameters.RequestedPublishingInterval, gaps_ms=gaps,
            deadbands={name: len(hd.values) for name, (_, hd) in deadbands.items()})
        # Out of range, with the refusal's words in the diagnostics.
        n = await node(c, f"{args.drive}/SpeedSetpoint")
        params = ua.WriteParameters()
        params.NodesToWrite = [ua.WriteValue(NodeId=n.nodeid, AttributeId=ua.AttributeIds.Value, Value=ua.DataValue(ua.Variant(99999.0, ua.VariantType.Double)))]
        req = ua.WriteRequest()
        req.Parameters = params
        req.RequestHeader.ReturnDiagnostics = 0x3FF
        from asyncua.ua.ua_binary import struct_from_binary
        r = struct_from_binary(ua.WriteResponse, await c.uaclient.session._send_request(req))
        diag = r.DiagnosticInfos[0].AdditionalInfo if r.DiagnosticInfos else None
        say("out-of-range", status=r.Results[0].name, diagnostics=diag)
        # A mode the drive does not have.
        try:
            await call(c, args.drive, "SetMode", ua.Variant("fast", ua.VariantType.String))
            say("set-mode-wrong", status="Good")
        except ua.UaStatusCodeError as e:
            say("set-mode-wrong", status=status_name(e))
        await call(c, args.drive, "Brake")
        say("called", method="Brake")


async def late(args):
    """As --user: SetMode("speed") and Activate(), then "ready"; once the
    file --go exists, SpeedSetpoint = --value with a request timeout, and
    so a TimeoutHint, of --hint-ms: "written" says what came back (the
    client's own timeout, or the server's status) and after how long; the
    session is closed once --go.end exists."""
    async with await client(args) as c:
        for method, inputs in [("SetMode", [ua.Variant("speed", ua.VariantType.String)]), ("Activate", [])]:
            await call(c, args.drive, method, *inputs)
        say("ready")
        while not os.path.exists(args.go):
            await asyncio.sleep(0.01)
        c.uaclient.protocol.timeout = args.hint_ms / 1000
        t0 = time.monotonic()
        try:
            got = await write(c, args.drive, "SpeedSetpoint", args.value)
        except asyncio.TimeoutError:
            got = "timeout"
        say("written", status=got, seconds=round(time.monotonic() - t0, 3))
        c.uaclient.protocol.timeout = 20
        # The session stays open (its end would stop the drive) until the
        # file --go.end exists.
        while not os.path.exists(args.go + ".end"):
            await asyncio.sleep(0.01)


async def lease(args):
    """Takes a lease (SetMode, Activate, a setpoint) and waits to be killed."""
    c = await client(args, timeout_ms=args.timeout_ms)
    await c.connect()
    say("session", timeout_ms=c.session_timeout, address=local_address(c))
    await call(c, args.drive, "SetMode", ua.Variant("speed", ua.VariantType.String))
    await call(c, args.drive, "Activate")
    got = await write(c, args.drive, "SpeedSetpoint", args.value)
    say("leased", status=got)
    await asyncio.sleep(3600)


async def brake(args):
    """Brake() on --drive (an operator's work), signed in as given."""
    try:
        async with await client(args) as c:
            try:
                await call(c, args.drive, "Brake")
                status = "Good"
            except ua.UaStatusCodeError as e:
                status = status_name(e)
            say("brake", status=status)
    except ua.UaStatusCodeError as e:
        say("session", status=status_name(e))
    except Exception as e:  # refused sign-ins surface as other errors too
        say("session", status=type(e).__name__, message=str(e))


async def secure(args):
    """A session on a signed and encrypted endpoint with --cert."""
    try:
        async with await client(args) as c:
            v = await (await node(c, f"{args.drive}/Speed")).read_value()
            say("secure", status="Good", speed=v)
    except Exception as e:  # the refusal is what some runs are for
        say("secure", status=status_name(e), message=str(e))


async def quality(args):
    """Follows a variable's status codes (no filter: the default trigger)."""
    async with await client(args) as c:
        h = Handler()
        sub = await c.create_subscription(50, h)
        await sub.subscribe_data_change(await node(c, f"{args.drive}/{args.variable}"), sampling_interval=0, queuesize=10)
        say("subscribed")
        await asyncio.sleep(args.seconds)


async def events(args):
    """Alarm events (AlarmConditionType, the client's default filter):
    prints each, and acknowledges the first active one for --drive; and,
    in a subscription of its own, --drive's --variable (no filter: the
    default trigger), each value with its status."""
    async with await client(args) as c:
        # Quiet: async-opcua sends an event item a data change of its own
        # (BadWaitingForInitialData) when it is created; only the values'
        # subscription's are printed.
        h = Handler(quiet=True)
        sub = await c.create_subscription(50, h)
        alarm_type = c.get_node(ua.ObjectIds.AlarmConditionType)
        evf = await get_filter_from_event_type([alarm_type])
        await sub.subscribe_events(c.nodes.server, alarm_type, evfilter=evf, queuesize=100)
        values = await c.create_subscription(50, Handler())
        await values.subscribe_data_change(await node(c, f"{args.drive}/{args.variable}"), sampling_interval=0, queuesize=10)
        say("subscribed")
        t0, seen, acked = time.monotonic(), 0, None
        while time.monotonic() - t0 < args.seconds:
            while seen < len(h.events):
                ev = h.events[seen]
                seen += 1
                fields = {k: str(getattr(ev, k, None)) for k in ["SourceName", "Message", "Severity", "ConditionName", "Retain", "ActiveState", "AckedState", "NodeId"]}
                say("event", **fields)
                if acked is None and getattr(ev, "SourceName", None) == args.drive and "True" not in str(getattr(ev, "AckedState", "")):
                    cond = getattr(ev, "NodeId", None)
                    try:
                        await c.get_node(cond).call_method(
                            ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge),
                            ua.Variant(ev.EventId, ua.VariantType.ByteString),
                            ua.LocalizedText("seen over OPC UA"),
                        )
                        acked = "Good"
                    except ua.UaStatusCodeError as e:
                        acked = status_name(e)
                    say("acknowledged", status=acked, condition=str(cond))
            await asyncio.sleep(0.05)


async def history(args):
    async with await client(args) as c:
        speed = await node(c, f"{args.drive}/Speed")
        end = datetime.now(timezone.utc)
        start = end - timedelta(hours=1)
        vals = await speed.read_raw_history(start, end, numvalues=0)
        five = await speed.read_raw_history(start, end, numvalues=5)
        say(
            "history",
            count=len(vals),
            first=vals[0].SourceTimestamp if vals else None,
            last=vals[-1].SourceTimestamp if vals else None,
            values=sorted({round(v.Value.Value) for v in vals if v.Value is not None and v.Value.Value is not None}),
            five=len(five),
        )


async def hold(args):
    """A session (anonymous, or --user) held open until stdin closes; then
    closed (CloseSession)."""
    async with await client(args) as c:
        say("connected", address=local_address(c))
        loop = asyncio.get_running_loop()
        reader = asyncio.StreamReader()
        await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
        await reader.read()
    say("closed")


async def table(args):
    """Requests read from stdin, one JSON object a line: {"user", "password"
    (absent: anonymous), "op": "write", "path": "lift/SpeedSetpoint",
    "value"} or {"op": "call", "object": "lift", "method": "lift/Brake"};
    answers {"step": "result", "status": ...} for each. One session per
    user, kept open."""
    sessions = {}
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader()
    await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
    say("ready")
    try:
        while line := await reader.readline():
            req = json.loads(line)
            user = req.get("user")
            if user not in sessions:
                args.user, args.password = user, req.get("password")
                c = await client(args)
                await c.connect()
                sessions[user] = c
            c = sessions[user]
            try:
                if req["op"] == "write":
                    n = await node(c, req["path"])
                    await n.write_value(ua.DataValue(ua.Variant(float(req["value"]), ua.VariantType.Double)))
                else:
                    await (await node(c, req["object"])).call_method(await node(c, req["method"]))
                status = "Good"
            except ua.UaStatusCodeError as e:
                status = status_name(e)
            say("result", status=status)
    finally:
        for c in sessions.values():
            await c.disconnect()


def clear_user_auth(self, params, username, password):
    """asyncua's `_add_user_auth` made to misbehave: the password in clear
    (no EncryptionAlgorithm) whatever the server's user token policy says."""
    params.UserIdentityToken = ua.UserNameIdentityToken()
    params.UserIdentityToken.UserName = username
    params.UserIdentityToken.Password = password.encode("utf8")
    params.UserIdentityToken.EncryptionAlgorithm = None
    params.UserIdentityToken.PolicyId = self.server_policy(ua.UserTokenType.UserName).PolicyId


async def sign_in_and_brake(args, user, password, clear=False):
    """Signs in as `user` (None: anonymous) and calls Brake() on --drive:
    the status of the sign-in or of the call, and the time it took."""
    args.user, args.password = user, password
    t0 = time.monotonic()
    try:
        c = await client(args)
        if clear:
            c._add_user_auth = clear_user_auth.__get__(c)
        async with c:
            try:
                await call(c, args.drive, "Brake")
                status = "Good"
            except ua.UaStatusCodeError as e:
                status = status_name(e)
            address = local_address(c)
    except ua.UaStatusCodeError as e:
        status, address = status_name(e), None
    except Exception as e:  # a refused activation surfaces as other errors too
        status, address = f"refused: {type(e).__name__}: {e}", None
    return {"status": status, "seconds": round(time.monotonic() - t0, 3), "address": address}


async def sign_in(args):
    """Signs in as given and calls Brake() on --drive, timed from the
    connection's start to the answer."""
    say("sign-in", **await sign_in_and_brake(args, args.user, args.password))


async def clear_password(args):
    """The operator's password sent in clear on the endpoint without
    security (refused), then encrypted as the user token policy says
    (accepted)."""
    user, password = args.user, args.password
    say("clear-password", **await sign_in_and_brake(args, user, password, clear=True))
    say("encrypted-password", **await sign_in_and_brake(args, user, password))


async def guess(args):
    """--guesses wrong passwords for --user from --source, then the right one
    from there (refused while paused), then the right one from the default
    address (signed in), timed."""
    user, password, source = args.user, args.password, args.source
    statuses = []
    for i in range(args.guesses):
        statuses.append((await sign_in_and_brake(args, user, f"wrong-{i}"))["status"])
    say("guessed", statuses=statuses)
    say("paused", **await sign_in_and_brake(args, user, password))
    args.source = None
    say("elsewhere", **await sign_in_and_brake(args, user, password))
    args.source = source


async def claim(args):
    """Signed in as given (a user certificate, with --cert as the
    application's): writes SpeedSetpoint and Settings/CurrentLimit."""
    try:
        async with await client(args) as c:
            out = {}
            for name, value in [("SpeedSetpoint", 100.0), ("Settings/CurrentLimit", 3.0)]:
                out[name] = await write(c, args.drive, name, value)
            say("claim", session="Good", **out)
    except Exception as e:  # the refusal of the session is what the run is for
        say("claim", session=f"{type(e).__name__}: {e}")


async def flood(args):
    """--sessions anonymous sessions (from --source), each with
    --subscriptions subscriptions of --items monitored items on --drive's
    Angle with queues of --queue, and never a Publish request (the requests
    are sent raw, so asyncua starts no publish loop). Says what each
    CreateMonitoredItems got, then holds the sessions until stdin closes."""
    from asyncua.ua.ua_binary import struct_from_binary
    sessions, results = [], {}
    for s in range(args.sessions):
        c = await client(args)
        await c.connect()
        sessions.append(c)
        angle = (await node(c, f"{args.drive}/Angle")).nodeid
        for _ in range(args.subscriptions):
            req = ua.CreateSubscriptionRequest()
            req.Parameters = ua.CreateSubscriptionParameters(
                RequestedPublishingInterval=1000, RequestedLifetimeCount=3000,
                RequestedMaxKeepAliveCount=1000, MaxNotificationsPerPublish=0,
                PublishingEnabled=True, Priority=0)
            r = struct_from_binary(ua.CreateSubscriptionResponse, await c.uaclient.session._send_request(req))
            sub = r.Parameters.SubscriptionId
            for first in range(0, args.items, 1000):
                req = ua.CreateMonitoredItemsRequest()
                req.Parameters.SubscriptionId = sub
                req.Parameters.TimestampsToReturn = ua.TimestampsToReturn.Both
                req.Parameters.ItemsToCreate = [
                    ua.MonitoredItemCreateRequest(
                        ItemToMonitor=ua.ReadValueId(NodeId=angle, AttributeId=ua.AttributeIds.Value),
                        MonitoringMode=ua.MonitoringMode.Reporting,
                        RequestedParameters=ua.MonitoringParameters(
                            ClientHandle=first + i, SamplingInterval=0, QueueSize=args.queue, DiscardOldest=True))
                    for i in range(min(1000, args.items - first))]
                data = await c.uaclient.session._send_request(req)
                r = struct_from_binary(ua.CreateMonitoredItemsResponse, data)
                for res in r.Results:
                    key = f"session{s} {res.StatusCode.name} queue {res.RevisedQueueSize}"
                    results[key] = results.get(key, 0) + 1
    say("flooded", results=results)
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader()
    await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
    await reader.read()
    for c in sessions:
        try:
            await c.disconnect()
        except Exception:
            pass
    say("closed")


SCENARIOS = {f.__name__.replace("_", "-"): f for f in [endpoints, browse, read, described, anonymous_write, operate, late, lease, hold, brake, secure, quality, events, history, table, sign_in, clear_password, guess, claim, flood]}


def scenarios(text):
    """SCENARIO, or several, comma-separated, run one after the other in
    this process (one interpreter start for them all)."""
    names = text.split(",")
    for name in names:
        if name not in SCENARIOS:
            raise argparse.ArgumentTypeError(f"unknown scenario {name!r}: {', '.join(SCENARIOS)}")
    return names


async def main():
    p = argparse.ArgumentParser()
    p.add_argument("url")
    p.add_argument("scenario", type=scenarios)
    p.add_argument("--drive", default="conveyor")
    p.add_argument("--variable", default="Speed")
    p.add_argument("--user")
    p.add_argument("--password")
    p.add_argument("--policy", default="none", choices=POLICIES)
    p.add_argument("--cert")
    p.add_argument("--key")
    p.add_argument("--user-cert")
    p.add_argument("--user-key")
    p.add_argument("--value", type=float, default=600.0)
    p.add_argument("--seconds", type=float, default=20)
    p.add_argument("--timeout-ms", type=int, default=3000)
    p.add_argument("--hint-ms", type=int, default=1000, help="the late scenario's request timeout")
    p.add_argument("--go", help="the late scenario's signal: a file that appears")
    p.add_argument("--metrics", help="the daemon's /metrics URL")
    p.add_argument("--source", help="the client's own address (a loopback address of its own)")
    p.add_argument("--guesses", type=int, default=10)
    p.add_argument("--sessions", type=int, default=2)
    p.add_argument("--subscriptions", type=int, default=10)
    p.add_argument("--items", type=int, default=1000)
    p.add_argument("--queue", type=int, default=1000)
    args = p.parse_args()
    for name in args.scenario:
        await SCENARIOS[name](args)


if __name__ == "__main__":
    asyncio.run(main())

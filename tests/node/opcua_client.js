// An OPC UA client on node-opcua (npm node-opcua-client, installed under
// target/node-opcua by scripts/test), the second implementation the OPC UA
// tests (tests/control/opcua.rs) check the server with; one scenario per run,
// or several (comma-separated) one after the other:
//   node opcua_client.js URL SCENARIO[,SCENARIO...] --pki DIR [--drive D] [--user U --password P]
// Prints one JSON object per line ({"step": ...}) for the test to check;
// {"step": "error"} and exit status 1 when a step cannot go on.
"use strict";
const {
    OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, UserTokenType,
    DataType, ClientSubscription, ClientMonitoredItem, TimestampsToReturn,
    constructEventFilter, ObjectIds, resolveNodeId, coerceNodeId, Variant,
} = require("node-opcua-client");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");

const [url, scenario] = process.argv.slice(2, 4);
const opt = (name, fallback) => {
    const i = process.argv.indexOf(`--${name}`);
    return i > 0 ? process.argv[i + 1] : fallback;
};
const drive = opt("drive", "conveyor");
const NS = "urn:drivegate:drives";

const say = (step, fields = {}) => console.log(JSON.stringify({ step, ...fields }));
const fail = (what, fields = {}) => { say("error", { what, ...fields }); process.exit(1); };
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

async function connect(user, timeout) {
    const client = OPCUAClient.create({
        applicationName: "drivegate-tests",
        applicationUri: "urn:node-opcua-client",
        securityMode: MessageSecurityMode.None,
        securityPolicy: SecurityPolicy.None,
        clientCertificateManager: new OPCUACertificateManager({
            rootFolder: opt("pki"), automaticallyAcceptUnknownCertificate: true,
        }),
        endpointMustExist: false,
        connectionStrategy: { maxRetry: 0 },
        requestedSessionTimeout: timeout || 30000,
    });
    await client.connect(url);
    const identity = user
        ? { type: UserTokenType.UserName, userName: opt("user"), password: opt("password") }
        : { type: UserTokenType.Anonymous };
    const session = await client.createSession(identity);
    const ns = (await session.readNamespaceArray()).indexOf(NS);
    return { client, session, ns, id: (s) => coerceNodeId(`ns=${ns};s=Drives/${s}`) };
}

async function close(c) {
    await c.session.close();
    await c.client.disconnect();
}

const double = (value) => ({ value: { dataType: DataType.Double, value } });

async function call(c, method, args = []) {
    const r = await c.session.call({ objectId: c.id(drive), methodId: c.id(`${drive}/${method}`), inputArguments: args });
    return r.statusCode.name;
}

const scenarios = {
    async endpoints() {
        const client = OPCUAClient.create({ endpointMustExist: false, connectionStrategy: { maxRetry: 0 } });
        await client.connect(url);
        const eps = await client.getEndpoints();
        say("endpoints", { endpoints: eps.map((e) => ({
            policy: e.securityPolicyUri.split("#")[1],
            mode: MessageSecurityMode[e.securityMode],
            tokens: e.userIdentityTokens.map((t) => UserTokenType[t.tokenType]).sort(),
        })) });
        await client.disconnect();
    },

    async browse() {
        const c = await connect();
        const drives = await c.session.browse(coerceNodeId(`ns=${c.ns};s=Drives`));
        const children = await c.session.browse(c.id(drive));
        say("browse", {
            drives: drives.references.map((x) => x.browseName.name).sort(),
            children: children.references.map((x) => x.browseName.name).sort(),
        });
        await close(c);
    },

    async described() {
        const c = await connect();
        const children = await c.session.browse(c.id(drive));
        const order = children.references.filter((r) => r.isForward && r.nodeClass !== 0)
            .filter((r) => r.referenceTypeId.toString() !== "ns=0;i=40")
            .map((x) => x.browseName.name);
        const missing = [];
        for (const r of children.references) {
            const d = await c.session.read({ nodeId: r.nodeId, attributeId: AttributeIds.Description });
            if (d.statusCode.name !== "Good" || !d.value.value || !d.value.value.text) {
                missing.push(`${r.browseName.name}: ${d.statusCode.name}`);
            }
        }
        const dt = (await c.session.read({ nodeId: c.id(`${drive}/Mode`), attributeId: AttributeIds.DataType })).value.value;
        const dtName = (await c.session.read({ nodeId: dt, attributeId: AttributeIds.BrowseName })).value.value.name;
        const props = await c.session.browse(dt);
        const strings = props.references.find((r) => r.browseName.name === "EnumStrings");
        const values = strings
            ? (await c.session.read({ nodeId: strings.nodeId, attributeId: AttributeIds.Value })).value.value.map((t) => t.text)
            : null;
        say("described", { order, missing, mode_type: dtName, enum_strings: values });
        await close(c);
    },

    async read() {
        const c = await connect();
        const values = {};
        for (const v of ["Speed", "Temperature", "Voltage"]) {
            const dv = await c.session.read({ nodeId: c.id(`${drive}/${v}`), attributeId: AttributeIds.Value });
            const eu = (await c.session.read({ nodeId: c.id(`${drive}/${v}/EngineeringUnits`), attributeId: AttributeIds.Value })).value.value;
            const range = (await c.session.read({ nodeId: c.id(`${drive}/${v}/EURange`), attributeId: AttributeIds.Value })).value.value;
            values[v] = { value: dv.value.value, status: dv.statusCode.name, source_timestamp: dv.sourceTimestamp,
                unit: eu.displayName.text, unit_id: eu.unitId, low: range.low, high: range.high };
        }
        say("read", { values });
        await close(c);
    },

    async operate() {
        let c = await connect();
        let st = await c.session.write({ nodeId: c.id(`${drive}/SpeedSetpoint`), attributeId: AttributeIds.Value, value: double(100) });
        say("anonymous-write", { status: st.name });
        await close(c);
        c = await connect(true);
        const sub = ClientSubscription.create(c.session, { requestedPublishingInterval: 50, requestedMaxKeepAliveCount: 10, publishingEnabled: true });
        const item = ClientMonitoredItem.create(sub, { nodeId: c.id(`${drive}/Speed`), attributeId: AttributeIds.Value },
            { samplingInterval: 0, queueSize: 10, discardOldest: true }, TimestampsToReturn.Both);
        const seen = [];
        item.on("changed", (dv) => seen.push(dv.value.value));
        say("called", { method: "SetMode", status: await call(c, "SetMode", [new Variant({ dataType: DataType.String, value: "speed" })]) });
        say("called", { method: "Activate", status: await call(c, "Activate") });
        const value = Number(opt("value", "450"));
        st = await c.session.write({ nodeId: c.id(`${drive}/SpeedSetpoint`), attributeId: AttributeIds.Value, value: double(value) });
        say("written", { status: st.name });
        const t0 = Date.now();
        while (Date.now() - t0 < 20000 && !(seen.length && Math.abs(seen[seen.length - 1] - value) < 1)) await sleep(50);
        say("turned", { reached: seen.length ? seen[seen.length - 1] : null });
        st = await c.session.write({ nodeId: c.id(`${drive}/SpeedSetpoint`), attributeId: AttributeIds.Value, value: double(99999) });
        say("out-of-range", { status: st.name });
        say("called", { method: "Brake", status: await call(c, "Brake") });
        await sub.terminate();
        await close(c);
    },

    async history() {
        const c = await connect();
        const end = new Date(), start = new Date(end.getTime() - 3600 * 1000);
        const r = await c.session.readHistoryValue(c.id(`${drive}/Speed`), start, end);
        const values = r.historyData && r.historyData.dataValues ? r.historyData.dataValues : [];
        say("history", { status: r.statusCode.name, count: values.length });
        await close(c);
    },

    async events() {
        const c = await connect(true);
        const sub = ClientSubscription.create(c.session, { requestedPublishingInterval: 50, publishingEnabled: true });
        const fields = ["EventId", "SourceName", "Message", "ConditionName", "AckedState", "ConditionId"];
        const filter = constructEventFilter(fields, resolveNodeId("AlarmConditionType"));
        const item = ClientMonitoredItem.create(sub, { nodeId: resolveNodeId(ObjectIds.Server), attributeId: AttributeIds.EventNotifier },
            { queueSize: 100, filter, discardOldest: true }, TimestampsToReturn.Both);
        const events = [];
        item.on("changed", (values) => events.push(values));
        await sleep(300);
        say("subscribed");
        const t0 = Date.now();
        let acked = false;
        while (Date.now() - t0 < Number(opt("seconds", "20")) * 1000) {
            while (events.length) {
                const ev = Object.fromEntries(fields.map((f, i) => [f, events[0][i].value]));
                events.shift();
                const acked_state = ev.AckedState && ev.AckedState.text;
                say("event", { source: ev.SourceName, message: ev.Message && ev.Message.text, acked: acked_state });
                if (!acked && ev.SourceName === drive && acked_state !== "Acknowledged") {
                    const st = await c.session.acknowledgeCondition(ev.ConditionId, ev.EventId, "seen over OPC UA");
                    say("acknowledged", { status: st.name });
                    acked = true;
                }
            }
            await sleep(50);
        }
        await sub.terminate();
        await close(c);
    },

    async lease() {
        const c = await connect(true, Number(opt("timeout-ms", "3000")));
        await call(c, "SetMode", [new Variant({ dataType: DataType.String, value: "speed" })]);
        await call(c, "Activate");
        const st = await c.session.write({ nodeId: c.id(`${drive}/SpeedSetpoint`), attributeId: AttributeIds.Value, value: double(Number(opt("value", "300"))) });
        say("leased", { status: st.name, timeout_ms: c.session.timeout });
        await sleep(3600 * 1000);
    },
};

(async () => {
    // One scenario, or several (comma-separated) one after the other: one
    // start of node and node-opcua for them all.
    const names = scenario.split(",");
    for (const name of names) if (!scenarios[name]) fail(`unknown scenario ${name}`);
    for (const name of names) {
        try {
            await scenarios[name]();
        } catch (e) {
            fail(name, { message: e.message });
        }
    }
    process.exit(0);
})();

//! A small Chrome DevTools Protocol client: Debian's chromium, headless,
//! driven over its DevTools WebSocket with the tokio-tungstenite the other
//! tests use already. CDP gives what the console tests need beside clicks:
//! every request the page makes (to prove none leaves loopback), console
//! messages and exceptions, real pointer and key events (held, for
//! hold-to-jog), closing a tab, screenshots and the renderer's CPU time.

use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures_util::{SinkExt, StreamExt};
use serde_json::{Value, json};
use tokio::sync::{Notify, mpsc, oneshot};
use tokio_tungstenite::tungstenite::Message;

/// The flags every start uses: headless, nothing that reaches for the
/// network on its own (the machine has none; without them chromium tries
/// to reach its maker's services), and no tab's timers or renderer slowed
/// for being in the background or occluded, as a test's tab may be (the
/// console draws on timers and animation frames).
pub const FLAGS: &[&str] = &[
    "--headless",
    "--disable-background-timer-throttling",
    "--disable-backgrounding-occluded-windows",
    "--disable-renderer-backgrounding",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-default-apps",
    "--disable-extensions",
    "--disable-domain-reliability",
    "--disable-client-side-phishing-detection",
    "--metrics-recording-only",
    "--password-store=basic",
    "--use-mock-keychain",
    "--remote-debugging-address=127.0.0.1",
    "--remote-debugging-port=0",
];

/// Where Debian installs chromium.
pub const CHROMIUM: &str = "/usr/bin/chromium";

type Pending = Arc<Mutex<HashMap<u64, oneshot::Sender<Result<Value, String>>>>>;

/// Everything the browser told us without being asked, in order.
#[derive(Default)]
pub struct Events {
    list: Mutex<Vec<Value>>,
    changed: Notify,
}

impl Events {
    /// A copy of the events so far.
    pub fn all(&self) -> Vec<Value> {
        self.list.lock().unwrap().clone()
    }
}

/// A running chromium and the connection to it.
pub struct Browser {
    child: tokio::process::Child,
    _profile: tempfile::TempDir,
    out: mpsc::UnboundedSender<String>,
    pending: Pending,
    next: Arc<AtomicU64>,
    /// Events of every page.
    pub events: Arc<Events>,
    /// The renderer process ids are not known to CDP; the browser's is.
    pub pid: u32,
}

/// One tab, attached with its own session.
pub struct Page {
    browser_out: mpsc::UnboundedSender<String>,
    pending: Pending,
    next: Arc<AtomicU64>,
    events: Arc<Events>,
    /// The target id (to close the tab).
    pub target: String,
    /// The CDP session id of the tab.
    pub session: String,
}

impl Browser {
    /// Starts chromium with a fresh profile. A missing chromium is a test
    /// failure that names the Debian package, never a skip.
    pub async fn start(extra: &[&str]) -> Browser {
        assert!(
            Path::new(CHROMIUM).exists(),
            "{CHROMIUM} is missing: the console tests need Debian's chromium (apt-get install chromium)"
        );
        let profile = tempfile::tempdir().unwrap();
        let mut command = tokio::process::Command::new(CHROMIUM);
        command
            .args(FLAGS)
            .args(extra)
            .arg(format!("--user-data-dir={}", profile.path().display()))
            .arg("about:blank")
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .kill_on_drop(true);
        let child = command.spawn().expect("chromium starts");
        let pid = child.id().unwrap_or(0);
        // chromium writes its DevTools port and path here once it listens.
        let port_file = profile.path().join("DevToolsActivePort");
        let start = Instant::now();
        let text = loop {
            if let Ok(t) = std::fs::read_to_string(&port_file)
                && t.lines().count() >= 2
            {
                break t;
            }
            assert!(
                start.elapsed() < Duration::from_secs(60),
                "chromium did not open its DevTools port within 60 s"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        let mut lines = text.lines();
        let port = lines.next().unwrap().trim();
        let path = lines.next().unwrap().trim();
        let url = format!("ws://127.0.0.1:{port}{path}");
        let (socket, _) = tokio_tungstenite::connect_async(&url)
            .await
            .expect("DevTools connection");
        let (mut sink, mut source) = socket.split();
        let (out, mut out_rx) = mpsc::unbounded_channel::<String>();
        tokio::spawn(async move {
            while let Some(text) = out_rx.recv().await {
                if sink.send(Message::text(text)).await.is_err() {
                    return;
                }
            }
        });
        let pending: Pending = Arc::default();
        let events = Arc::new(Events::default());
        {
            let pending = pending.clone();
            let events = events.clone();
            tokio::spawn(async move {
                while let Some(Ok(message)) = source.next().await {
                    let Message::Text(text) = message else {
                        continue;
                    };
                    let Ok(value) = serde_json::from_str::<Value>(&text) else {
                        continue;
                    };
                    if let Some(id) = value.get("id").and_then(Value::as_u64) {
                        if let Some(tx) = pending.lock().unwrap().remove(&id) {
                            let result = match value.get("error") {
                                Some(e) => Err(e.to_string()),
                                None => Ok(value.get("result").cloned().unwrap_or(Value::Null)),
                            };
                            let _ = tx.send(result);
                        }
                    } else {
                        events.list.lock().unwrap().push(value);
                        events.changed.notify_waiters();
                    }
                }
            });
        }
        Browser {
            child,
            _profile: profile,
            out,
            pending,
            next: Arc::new(AtomicU64::new(1)),
            events,
            pid,
        }
    }

    async fn call(&self, method: &str, params: Value) -> Value {
        send(&self.out, &self.pending, &self.next, None, method, params)
            .await
            .unwrap_or_else(|e| panic!("{method}: {e}"))
    }

    /// Opens a new tab on `about:blank`, with the page, runtime, log and
    /// network domains on, at `width` x `height`.
    pub async fn new_page(&self, width: u32, height: u32) -> Page {
        let target = self
            .call("Target.createTarget", json!({"url": "about:blank"}))
            .await["targetId"]
            .as_str()
            .unwrap()
            .to_string();
        let session = self
            .call(
                "Target.attachToTarget",
                json!({"targetId": target, "flatten": true}),
            )
            .await["sessionId"]
            .as_str()
            .unwrap()
            .to_string();
        let page = Page {
            browser_out: self.out.clone(),
            pending: self.pending.clone(),
            next: self.next.clone(),
            events: self.events.clone(),
            target,
            session,
        };
        for domain in ["Page", "Runtime", "Log", "Network", "Performance"] {
            page.call(&format!("{domain}.enable"), json!({})).await;
        }
        page.call(
            "Emulation.setDeviceMetricsOverride",
            json!({"width": width, "height": height, "deviceScaleFactor": 1, "mobile": false}),
        )
        .await;
        page
    }

    /// Closes the tab as a user closing it would: its sockets close.
    pub async fn close_page(&self, page: &Page) {
        self.call("Target.closeTarget", json!({"targetId": page.target}))
            .await;
    }

    /// Lets pages save downloads into `dir` under the names the server
    /// gives them; the browser reports each one (`Browser.downloadWillBegin`,
    /// `Browser.downloadProgress`).
    pub async fn allow_downloads(&self, dir: &Path) {
        self.call(
            "Browser.setDownloadBehavior",
            json!({"behavior": "allow", "downloadPath": dir, "eventsEnabled": true}),
        )
        .await;
    }

    /// Downloads completed so far.
    pub fn downloads_done(&self) -> usize {
        self.events
            .all()
            .iter()
            .filter(|e| {
                e["method"] == "Browser.downloadProgress" && e["params"]["state"] == "completed"
            })
            .count()
    }

    /// Waits until more than `seen` downloads completed, and returns the
    /// file name of the next one (in the download directory). A cancelled
    /// download fails.
    pub async fn wait_download(&self, seen: usize, limit: Duration) -> String {
        let start = Instant::now();
        loop {
            let notified = self.events.changed.notified();
            let all = self.events.all();
            let done: Vec<&Value> = all
                .iter()
                .filter(|e| {
                    e["method"] == "Browser.downloadProgress" && e["params"]["state"] == "completed"
                })
                .collect();
            if let Some(e) = done.get(seen) {
                let guid = &e["params"]["guid"];
                let begun = all
                    .iter()
                    .find(|b| {
                        b["method"] == "Browser.downloadWillBegin" && &b["params"]["guid"] == guid
                    })
                    .expect("a download that began");
                return begun["params"]["suggestedFilename"]
                    .as_str()
                    .unwrap()
                    .to_string();
            }
            assert!(
                !all.iter().any(|e| e["method"] == "Browser.downloadProgress"
                    && e["params"]["state"] == "canceled"),
                "a download was cancelled"
            );
            let left = limit.saturating_sub(start.elapsed());
            assert!(!left.is_zero(), "no download within {limit:?}");
            let _ = tokio::time::timeout(left, notified).await;
        }
    }

    /// Ends chromium.
    pub async fn stop(mut self) {
        let _ = self.child.start_kill();
        let _ = tokio::time::timeout(Duration::from_secs(10), self.child.wait()).await;
    }
}

async fn send(
    out: &mpsc::UnboundedSender<String>,
    pending: &Pending,
    next: &AtomicU64,
    session: Option<&str>,
    method: &str,
    params: Value,
) -> Result<Value, String> {
    let id = next.fetch_add(1, Ordering::Relaxed);
    let mut message = json!({"id": id, "method": method, "params": params});
    if let Some(s) = session {
        message["sessionId"] = json!(s);
    }
    let (tx, rx) = oneshot::channel();
    pending.lock().unwrap().insert(id, tx);
    out.send(message.to_string())
        .map_err(|_| "the DevTools connection is closed".to_string())?;
    match tokio::time::timeout(Duration::from_secs(60), rx).await {
        Ok(Ok(result)) => result,
        Ok(Err(_)) => Err("the DevTools connection closed".to_string()),
        Err(_) => Err("no answer within 60 s".to_string()),
    }
}

impl Page {
    /// Sends a CDP command to this tab.
    pub async fn call(&self, method: &str, params: Value) -> Value {
        self.try_call(method, params)
            .await
            .unwrap_or_else(|e| panic!("{method}: {e}"))
    }

    /// Sends a CDP command to this tab; the error as text.
    pub async fn try_call(&self, method: &str, params: Value) -> Result<Value, String> {
        send(
            &self.browser_out,
            &self.pending,
            &self.next,
            Some(&self.session),
            method,
            params,
        )
        .await
    }

    /// Loads `url` and waits for its load event.
    pub async fn goto(&self, url: &str) {
        let seen = self.events_of("Page.loadEventFired").len();
        self.call("Page.navigate", json!({"url": url})).await;
        self.wait_event("Page.loadEventFired", seen, Duration::from_secs(30))
            .await;
    }

    /// The value of a JavaScript expression (promises awaited).
    pub async fn eval(&self, expression: &str) -> Value {
        let r = self
            .call(
                "Runtime.evaluate",
                json!({"expression": expression, "returnByValue": true, "awaitPromise": true}),
            )
            .await;
        if let Some(e) = r.get("exceptionDetails") {
            panic!("{expression}: {e}");
        }
        r["result"]["value"].clone()
    }

    /// Waits until `expression` is truthy (checked on every change the page
    /// could have made: at most every 20 ms), and returns its value.
    pub async fn wait_for(&self, expression: &str, limit: Duration, what: &str) -> Value {
        let start = Instant::now();
        loop {
            let v = self.eval(expression).await;
            let truthy = match &v {
                Value::Null => false,
                Value::Bool(b) => *b,
                Value::Number(n) => n.as_f64() != Some(0.0),
                Value::String(s) => !s.is_empty(),
                _ => true,
            };
            if truthy {
                return v;
            }
            assert!(
                start.elapsed() < limit,
                "{what}: not seen within {limit:?} ({expression})"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// Events of this tab named `method`.
    pub fn events_of(&self, method: &str) -> Vec<Value> {
        self.events
            .all()
            .into_iter()
            .filter(|e| {
                e["method"] == method && e["sessionId"].as_str() == Some(self.session.as_str())
            })
            .collect()
    }

    /// Waits for more than `seen` events named `method`.
    pub async fn wait_event(&self, method: &str, seen: usize, limit: Duration) {
        let start = Instant::now();
        loop {
            let notified = self.events.changed.notified();
            if self.events_of(method).len() > seen {
                return;
            }
            let left = limit.saturating_sub(start.elapsed());
            assert!(!left.is_zero(), "{method} not seen within {limit:?}");
            let _ = tokio::time::timeout(left, notified).await;
        }
    }

    /// Every error the page reported: exceptions, console.error, and the
    /// browser's own error entries (CSP violations, failed loads).
    pub fn errors(&self) -> Vec<String> {
        let mut out = Vec::new();
        for e in self.events_of("Runtime.exceptionThrown") {
            out.push(format!("exception: {}", e["params"]["exceptionDetails"]));
        }
        for e in self.events_of("Runtime.consoleAPICalled") {
            if e["params"]["type"] == "error" || e["params"]["type"] == "assert" {
                out.push(format!("console.error: {}", e["params"]["args"]));
            }
        }
        for e in self.events_of("Log.entryAdded") {
            if e["params"]["entry"]["level"] == "error" {
                out.push(format!("log: {}", e["params"]["entry"]));
            }
        }
        out
    }

    /// The URL of every request and WebSocket the page opened.
    pub fn requests(&self) -> Vec<String> {
        let mut out: Vec<String> = self
            .events_of("Network.requestWillBeSent")
            .iter()
            .map(|e| {
                e["params"]["request"]["url"]
                    .as_str()
                    .unwrap_or("")
                    .to_string()
            })
            .collect();
        out.extend(
            self.events_of("Network.webSocketCreated")
                .iter()
                .map(|e| e["params"]["url"].as_str().unwrap_or("").to_string()),
        );
        out
    }

    /// The centre of the first element matching `selector`, in CSS pixels,
    /// scrolled into view.
    pub async fn centre(&self, selector: &str) -> (f64, f64) {
        let v = self
            .eval(&format!(
                "(() => {{ const el = document.querySelector({sel}); if (!el) return null; \
                 el.scrollIntoView({{block: 'center'}}); const r = el.getBoundingClientRect(); \
                 return [r.x + r.width / 2, r.y + r.height / 2]; }})()",
                sel = serde_json::to_string(selector).unwrap()
            ))
            .await;
        let a = v
            .as_array()
            .unwrap_or_else(|| panic!("no element {selector} on the page"));
        (a[0].as_f64().unwrap(), a[1].as_f64().unwrap())
    }

    /// Moves the mouse to the element and presses the left button (held).
    pub async fn mouse_down(&self, selector: &str) {
        let (x, y) = self.centre(selector).await;
        for kind in ["mouseMoved", "mousePressed"] {
            self.call(
                "Input.dispatchMouseEvent",
                json!({"type": kind, "x": x, "y": y, "button": "left", "buttons": 1, "clickCount": 1}),
            )
            .await;
        }
    }

    /// Releases the left button where it was pressed.
    pub async fn mouse_up(&self, selector: &str) {
        let (x, y) = self.centre(selector).await;
        self.call(
            "Input.dispatchMouseEvent",
            json!({"type": "mouseReleased", "x": x, "y": y, "button": "left", "buttons": 0, "clickCount": 1}),
        )
        .await;
    }

    /// A real click (press and release) on the element.
    pub async fn click(&self, selector: &str) {
        self.mouse_down(selector).await;
        self.mouse_up(selector).await;
    }

    /// Presses a key (`key` as in KeyboardEvent.key, `code`, the virtual
    /// key code, and modifiers: 8 is Shift).
    pub async fn key(&self, kind: &str, key: &str, code: &str, vk: u32, modifiers: u32) {
        let mut p = json!({"type": kind, "key": key, "code": code,
            "windowsVirtualKeyCode": vk, "nativeVirtualKeyCode": vk, "modifiers": modifiers});
        if kind == "keyDown" && key.chars().count() == 1 {
            p["text"] = json!(key);
        }
        self.call("Input.dispatchKeyEvent", p).await;
    }

    /// Types `text` into the element matching `selector` (replacing it).
    pub async fn fill(&self, selector: &str, text: &str) {
        self.eval(&format!(
            "(() => {{ const el = document.querySelector({sel}); el.focus(); el.select(); }})()",
            sel = serde_json::to_string(selector).unwrap()
        ))
        .await;
        self.call("Input.insertText", json!({"text": text})).await;
    }

    /// Chooses `files` in the file input matching `selector`, as a user
    /// picking them in the file dialog would (the input fires `change`).
    pub async fn set_files(&self, selector: &str, files: &[&Path]) {
        let r = self
            .call(
                "Runtime.evaluate",
                json!({"expression": format!("document.querySelector({})", serde_json::to_string(selector).unwrap())}),
            )
            .await;
        let object = r["result"]["objectId"]
            .as_str()
            .unwrap_or_else(|| panic!("no element {selector} on the page"))
            .to_string();
        let files: Vec<String> = files.iter().map(|f| f.display().to_string()).collect();
        self.call(
            "DOM.setFileInputFiles",
            json!({"files": files, "objectId": object}),
        )
        .await;
    }

    /// A PNG of the viewport (or the whole page with `full`).
    pub async fn screenshot(&self, path: &Path, full: bool) {
        let mut params = json!({"format": "png"});
        if full {
            let m = self.call("Page.getLayoutMetrics", json!({})).await;
            let size = &m["cssContentSize"];
            params["clip"] = json!({"x": 0, "y": 0, "width": size["width"], "height": size["height"], "scale": 1});
            params["captureBeyondViewport"] = json!(true);
        }
        let shot = self.call("Page.captureScreenshot", params).await;
        let data = shot["data"].as_str().unwrap();
        std::fs::write(path, base64_decode(data)).unwrap();
    }

    /// The renderer's metrics (Performance.getMetrics) by name.
    pub async fn metrics(&self) -> HashMap<String, f64> {
        let m = self.call("Performance.getMetrics", json!({})).await;
        m["metrics"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| {
                (
                    x["name"].as_str().unwrap().to_string(),
                    x["value"].as_f64().unwrap_or(0.0),
                )
            })
            .collect()
    }
}

/// Standard base64, as CDP sends screenshots.
fn base64_decode(text: &str) -> Vec<u8> {
    let value = |c: u8| -> Option<u32> {
        Some(match c {
            b'A'..=b'Z' => u32::from(c - b'A'),
            b'a'..=b'z' => u32::from(c - b'a') + 26,
            b'0'..=b'9' => u32::from(c - b'0') + 52,
            b'+' => 62,
            b'/' => 63,
            _ => return None,
        })
    };
    let mut out = Vec::with_capacity(text.len() * 3 / 4);
    let mut acc = 0u32;
    let mut bits = 0;
    for c in text.bytes() {
        let Some(v) = value(c) else { continue };
        acc = (acc << 6) | v;
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    out
}

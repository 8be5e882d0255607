//! What the API tests share: a configuration derived from `FOUR_DRIVES`, a
//! small JSON client over real HTTP, and WebSocket send/receive functions.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use futures_util::{SinkExt, StreamExt};
use reqwest::header::HeaderMap;
use serde_json::Value;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

use crate::support::config::ConfigBuilder;

/// `FOUR_DRIVES` with `http` keys added to `[http]` and `rest` (whole
/// tables, e.g. a `[safety]` section) appended.
pub fn config(http: &str, rest: &str) -> String {
    ConfigBuilder::four_drives().http(http).tables(rest).toml()
}

/// A response: status, headers and the JSON body (`Null` if not JSON).
#[derive(Debug)]
pub struct Reply {
    pub status: u16,
    pub headers: HeaderMap,
    pub body: Value,
}

impl Reply {
    /// The problem `type` after `urn:drivegate:problem:`.
    pub fn problem(&self) -> &str {
        self.body["type"]
            .as_str()
            .and_then(|t| t.strip_prefix("urn:drivegate:problem:"))
            .unwrap_or("")
    }

    /// The content type.
    pub fn content_type(&self) -> &str {
        self.headers
            .get("content-type")
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
    }

    /// Asserts the status and returns the body.
    pub fn expect(self, status: u16) -> Value {
        assert_eq!(self.status, status, "unexpected reply: {:#}", self.body);
        self.body
    }

    /// Asserts a problem of `kind` with `status`, sent as problem+json.
    pub fn expect_problem(self, status: u16, kind: &str) -> Value {
        assert_eq!(
            (self.status, self.problem()),
            (status, kind),
            "unexpected reply: {:#}",
            self.body
        );
        assert_eq!(self.content_type(), "application/problem+json");
        assert_eq!(self.body["status"], status);
        assert!(self.body["title"].is_string() && self.body["detail"].is_string());
        self.body
    }
}

/// A JSON client of one daemon, with an optional token.
#[derive(Clone)]
pub struct Api {
    base: String,
    token: Option<String>,
    http: reqwest::Client,
}

impl Api {
    pub fn new(addr: SocketAddr, token: Option<&str>) -> Self {
        Api {
            base: format!("http://{addr}"),
            token: token.map(str::to_string),
            http: reqwest::Client::builder()
                .timeout(Duration::from_secs(20))
                .build()
                .unwrap(),
        }
    }

    pub fn with_token(&self, token: Option<&str>) -> Self {
        Api {
            token: token.map(str::to_string),
            ..self.clone()
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    async fn send(&self, builder: reqwest::RequestBuilder) -> Reply {
        let builder = match &self.token {
            Some(t) => builder.bearer_auth(t),
            None => builder,
        };
        let response = builder.send().await.expect("request sent");
        let status = response.status().as_u16();
        let headers = response.headers().clone();
        let bytes = response.bytes().await.expect("body read");
        let body = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
        Reply {
            status,
            headers,
            body,
        }
    }

    pub async fn get(&self, path: &str) -> Reply {
        self.send(self.http.get(self.url(path))).await
    }

    pub async fn put(&self, path: &str, body: Value) -> Reply {
        self.send(self.http.put(self.url(path)).json(&body)).await
    }

    pub async fn post(&self, path: &str, body: Value) -> Reply {
        self.send(self.http.post(self.url(path)).json(&body)).await
    }

    pub async fn post_empty(&self, path: &str) -> Reply {
        self.send(self.http.post(self.url(path))).await
    }

    pub async fn delete(&self, path: &str) -> Reply {
        self.send(self.http.delete(self.url(path))).await
    }

    pub async fn raw(
        &self,
        builder: impl FnOnce(&reqwest::Client) -> reqwest::RequestBuilder,
    ) -> Reply {
        self.send(builder(&self.http)).await
    }

    /// `POST .../commands/{command}`, expecting success.
    pub async fn command(&self, drive: &str, command: &str) -> Value {
        self.post_empty(&format!("/api/v1/drives/{drive}/commands/{command}"))
            .await
            .expect(200)
    }

    /// Activates `drive` and puts it in `mode`.
    pub async fn activate_in(&self, drive: &str, mode: &str) {
        self.command(drive, "activate").await;
        self.put(
            &format!("/api/v1/drives/{drive}/mode"),
            serde_json::json!({ "mode": mode }),
        )
        .await
        .expect(200);
    }
}

pub type Ws = WebSocketStream<MaybeTlsStream<tokio::net::TcpStream>>;

/// Opens the stream (`query` like `?drives=all`), with a token if given.
pub async fn connect(addr: SocketAddr, query: &str, token: Option<&str>) -> Ws {
    let mut request = format!("ws://{addr}/api/v1/stream{query}")
        .into_client_request()
        .unwrap();
    if let Some(t) = token {
        request
            .headers_mut()
            .insert("authorization", format!("Bearer {t}").parse().unwrap());
    }
    let (ws, _) = tokio_tungstenite::connect_async(request)
        .await
        .expect("WebSocket connects");
    ws
}

/// Sends a JSON message.
pub async fn send_json(ws: &mut Ws, value: Value) {
    ws.send(Message::Text(value.to_string().into()))
        .await
        .expect("message sent");
}

/// The next JSON text message, within `limit`.
pub async fn next_json(ws: &mut Ws, limit: Duration) -> Value {
    let deadline = Instant::now() + limit;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let message = tokio::time::timeout(left, ws.next())
            .await
            .expect("a message in time")
            .expect("the stream is open")
            .expect("a valid frame");
        match message {
            Message::Text(t) => return serde_json::from_str(t.as_str()).expect("JSON text"),
            Message::Ping(_) | Message::Pong(_) => continue,
            other => panic!("unexpected frame {other:?}"),
        }
    }
}

/// Reads messages until one satisfies `want`, within `limit` (`want` sees
/// every message, so it may keep what it needs of the others).
pub async fn wait_for(
    ws: &mut Ws,
    limit: Duration,
    what: &str,
    mut want: impl FnMut(&Value) -> bool,
) -> Value {
    let deadline = Instant::now() + limit;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        assert!(!left.is_zero(), "no {what} within {limit:?}");
        let v = next_json(ws, left).await;
        if want(&v) {
            return v;
        }
    }
}

/// Sends a command and waits for its reply (other messages are skipped).
pub async fn ws_command(ws: &mut Ws, id: u64, op: &str, drive: &str, body: Value) -> Value {
    send_json(
        ws,
        serde_json::json!({"type": "command", "id": id, "op": op, "drive": drive, "body": body}),
    )
    .await;
    wait_for(ws, Duration::from_secs(10), "the reply", |v| {
        v["type"] == "reply" && v["id"] == id
    })
    .await
}

/// Reads the stream for `window` and returns every message.
pub async fn messages_within(ws: &mut Ws, window: Duration) -> Vec<Value> {
    let until = Instant::now() + window;
    let mut seen = Vec::new();
    loop {
        let left = until.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return seen;
        }
        match tokio::time::timeout(left, next_json(ws, left + Duration::from_secs(1))).await {
            Ok(v) => seen.push(v),
            Err(_) => return seen,
        }
    }
}

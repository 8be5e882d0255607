//! The REST + WebSocket face (`/api/v1`), with its OpenAPI document and
//! its authentication. Every write goes through the control core
//! ([`crate::control`]): this face authenticates, translates, calls the
//! core, and renders what it decided.
//!
//! - [`listener`] binds (loopback only without tokens) and limits connections,
//!   [`server`] serves them with a deadline on every request, [`guard`]
//!   refuses foreign hosts and foreign browser pages before any route runs,
//! - [`auth`] checks bearer tokens, [`throttle`] pauses addresses that
//!   guess them, [`caller`] turns a request into the core's `Caller` (the
//!   core's policy says which role may do what),
//! - [`drives`], [`commands`], [`setpoints`], [`settings`], [`readback`],
//!   [`document`], [`buses`], [`monitor`] (every frame on the wire),
//!   [`scope`] (triggered captures), [`alarms`], [`history`] (trends),
//!   [`whoami`] and [`health`] are the routes, all documented in
//!   [`openapi`] (the body schemas a derive cannot write are in
//!   [`body_schemas`]); they hand their writes to the core through
//!   [`crate::faces_shared`],
//! - [`extract`] reads requests, refusing bad ones with a problem document,
//! - [`hub`], [`stream`], [`stream_messages`] and [`stream_commands`] are
//!   the WebSocket stream,
//! - [`problem`] maps every error to `application/problem+json`.
//!
//! Handlers never touch a serial port: they submit jobs through the bus
//! handles of the [`Plant`] and wait for the drive's confirmation.

pub mod alarms;
pub mod auth;
pub mod body_schemas;
pub mod buses;
pub mod caller;
pub mod certificates;
pub mod config;
pub mod config_check;
pub mod config_commands;
pub mod config_file;
pub mod document;
pub mod drives;
pub mod extract;
pub mod guard;
pub mod health;
pub mod history;
pub mod hub;
pub mod listener;
pub mod listeners;
pub mod monitor;
pub mod monitor_live;
pub mod new_token;
pub mod openapi;
pub mod problem_response;
pub mod readback;
pub mod replacement;
pub mod request_metrics;
pub mod scope;
pub mod server;
pub mod setpoints;
pub mod settings;
pub mod settings_diff;
pub mod socket;
pub mod state;
pub mod stream;
pub mod stream_commands;
pub mod stream_messages;
pub mod throttle;
pub mod tokens;
pub mod whoami;

use crate::faces_shared::start::FaceStart;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::extract::DefaultBodyLimit;
use axum::middleware;
use tokio::task::JoinHandle;
use utoipa_swagger_ui::SwaggerUi;

use auth::Tokens;
use hub::Hub;
use listener::LimitedListener;
use problem_response::{Kind, Problem};
use state::ApiState;

/// Serves the API on `tcp` (bound by the caller where
/// [`listener::bind_address`] says), with `pages` (the web console, a face
/// of its own above this one) beside its routes, until `shutdown` fires.
/// Returns the bound address (the real port when the config said port 0)
/// and the task serving it.
pub(crate) async fn start(
    start: FaceStart,
    tcp: tokio::net::TcpListener,
    pages: Router<ApiState>,
) -> Result<(SocketAddr, JoinHandle<()>), String> {
    let FaceStart {
        config,
        plant,
        control,
        metrics,
        history,
        stop: shutdown,
    } = start;
    let config = &*config;
    let http = config.http.clone();
    let tokens = Tokens::resolve(&http.tokens, http.token_guesses)
        .map_err(|e| e.to_string())?
        .follow(&control);
    let addr = tcp.local_addr().map_err(|e| e.to_string())?;
    if tokens.is_empty() {
        if addr.ip() != http.listen.ip() {
            tracing::warn!(
                configured = %http.listen,
                listening = %addr,
                "no API tokens are configured: the API listens on loopback only, not on the configured address; add [[http.token]] sections to open it to the network"
            );
        } else {
            tracing::info!(
                listening = %addr,
                "no API tokens are configured: the API is open to local clients only, with full rights"
            );
        }
    } else {
        tracing::info!(tokens = tokens.len(), "API tokens loaded");
    }

    let tls = match &http.tls {
        None => None,
        Some(files) => {
            let config = crate::tls::Reloadable::load(
                files.clone(),
                crate::tls::ClientAuth::IfConfigured,
                &[b"http/1.1"],
            )
            .map(Arc::new)
            .map_err(|e| format!("[http.tls]: {e}"))?;
            let counter = metrics.clone();
            crate::tls::reload_on_hangup(
                config.clone(),
                "http",
                move |ok| counter.security().tls_reload("http", ok),
                shutdown.clone(),
            )
            .map_err(|e| format!("cannot watch for SIGHUP (certificate reloads): {e}"))?;
            tracing::info!(
                listening = %addr,
                mutual = files.client_ca.is_some(),
                "HTTPS only on this listener"
            );
            Some(server::Tls {
                config,
                metrics: metrics.clone(),
            })
        }
    };
    let hub = Hub::start(&plant, &control, &shutdown);
    scope::publish_progress(&plant, &hub, &shutdown);
    let state = ApiState::new(
        plant,
        metrics.clone(),
        http.clone(),
        tokens,
        control,
        history,
        hub,
        shutdown.clone(),
    );
    let app = app(state.clone(), pages);
    let listener = LimitedListener::new(tcp, listener::Limits::of(&http), metrics.clone());
    let header_timeout = http.header_timeout;
    let task = tokio::spawn(async move {
        server::serve(listener, app, header_timeout, tls, metrics, shutdown).await;
        // Upgraded connections are not the server's any more: the sessions
        // close themselves on shutdown, and are waited for here.
        state.sessions.close();
        if tokio::time::timeout(Duration::from_secs(3), state.sessions.wait())
            .await
            .is_err()
        {
            tracing::warn!("some WebSocket sessions did not close within 3 s");
        }
    });
    Ok((addr, task))
}

/// The whole HTTP application: the documented routes, `/openapi.json`,
/// `/docs`, `pages` (the web console: `/`, `/console/`), problem answers
/// for unknown routes, the body limit and the request counters.
pub fn app(state: ApiState, pages: Router<ApiState>) -> Router {
    let (routes, document) = openapi::router().split_for_parts();
    let docs: Router<ApiState> = SwaggerUi::new(openapi::DOCS_PATH)
        .url(
            openapi::DOCUMENT_PATH,
            openapi::document_for(document, state.control.lease_bounds()),
        )
        .into();
    routes
        .merge(docs)
        .merge(pages)
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(DefaultBodyLimit::max(state.config.max_body_bytes))
        .layer(middleware::from_fn_with_state(
            state.clone(),
            request_metrics::count,
        ))
        .layer(middleware::from_fn_with_state(
            guard::GuardState {
                guard: Arc::new(guard::BrowserGuard::new(
                    state.config.listen.ip(),
                    state.config.tls.is_some(),
                    &state.config.allowed_hosts,
                    &state.config.allowed_origins,
                )),
                metrics: state.metrics.clone(),
            },
            guard::guard,
        ))
        .with_state(state)
}

async fn not_found(uri: axum::http::Uri) -> Problem {
    Problem::new(
        Kind::NotFound,
        format!(
            "no route {}: the routes are listed at {} and {}",
            uri.path(),
            openapi::DOCS_PATH,
            openapi::DOCUMENT_PATH
        ),
    )
}

async fn method_not_allowed(method: axum::http::Method, uri: axum::http::Uri) -> Problem {
    Problem::new(
        Kind::MethodNotAllowed,
        format!(
            "{} does not take {method}; see {}",
            uri.path(),
            openapi::DOCS_PATH
        ),
    )
}

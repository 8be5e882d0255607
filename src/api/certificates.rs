//! The certificates, for an admin (the core's `Operation::Certificates`):
//!
//! - `GET /api/v1/certificates`: the OPC UA server's own, the client
//!   applications trusted and refused, user certificates and issuers, and
//!   the HTTPS and Modbus/TCP Security listeners' (with their client CAs):
//!   subject, issuer, application URI, validity, thumbprints;
//! - `POST /api/v1/certificates/{thumbprint}/trust`: a refused OPC UA
//!   client trusted; `DELETE /api/v1/certificates/{thumbprint}`: a trusted
//!   one removed (refused again); `POST
//!   /api/v1/certificates/opcua-server/renew`: the server's self-signed
//!   certificate made anew. Each applies without a restart of the daemon,
//!   audited by the core.

use std::time::SystemTime;

use axum::Json;
use axum::extract::State;
use serde::Serialize;
use utoipa::{IntoResponses, ToSchema};

use super::extract::PathParams;
use super::problem_response::{Kind, Problem, ProblemDetails};
use super::state::ApiState;
use crate::control::certificates::{Action, CertError, EXPIRY_WARNING_DAYS, Held};
use crate::control::{Caller, Rule};
use crate::faces_shared::writes::forbidden;
use crate::timestamp::rfc3339;

/// One certificate.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct CertificateView {
    /// What it is for: `opcua-server`, `opcua-trusted`, `opcua-rejected`,
    /// `opcua-user`, `opcua-issuer`, `https`, `https-client-ca`,
    /// `modbus-tls`, `modbus-tls-client-ca`.
    pub place: String,
    /// Its file.
    pub file: String,
    /// Its subject.
    pub subject: String,
    /// Its issuer.
    pub issuer: String,
    /// The URI of its subject alternative names (an OPC UA application's
    /// application URI).
    pub application_uri: Option<String>,
    /// Valid from (RFC 3339).
    pub not_before: String,
    /// Valid until (RFC 3339).
    pub not_after: String,
    /// Days left until it expires (negative: expired).
    pub days_left: i64,
    /// True when it expires within 30 days (or has): an alarm is raised.
    pub expiring: bool,
    /// SHA-1 of its DER, lowercase hex: the thumbprint OPC UA clients show.
    pub thumbprint: String,
    /// SHA-256 of its DER, lowercase hex.
    pub sha256: String,
    /// True when it is its own issuer.
    pub self_signed: bool,
}

impl CertificateView {
    fn of(h: &Held, now: SystemTime) -> Self {
        let days_left = h.info.days_left(now);
        CertificateView {
            place: h.place.name().to_string(),
            file: h.file.display().to_string(),
            subject: h.info.subject.clone(),
            issuer: h.info.issuer.clone(),
            application_uri: h.info.application_uri.clone(),
            not_before: rfc3339(h.info.not_before),
            not_after: rfc3339(h.info.not_after),
            days_left,
            expiring: days_left < EXPIRY_WARNING_DAYS,
            thumbprint: h.info.thumbprint.clone(),
            sha256: h.info.sha256.clone(),
            self_signed: h.info.self_signed(),
        }
    }
}

/// The certificates.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct CertificatesReply {
    /// Every certificate, by place.
    pub certificates: Vec<CertificateView>,
    /// What could not be read, and why; what is worth knowing.
    pub notes: Vec<String>,
}

/// What a change did.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct CertificateChange {
    /// What was done, in words.
    pub done: String,
    /// The certificate as it is now (the new one, after a renewal).
    pub certificate: Option<CertificateView>,
}

/// Errors of the certificate routes.
#[derive(IntoResponses)]
pub enum CertificateProblems {
    /// `unauthorized`: no token, or an unknown one.
    #[response(status = 401, content_type = "application/problem+json")]
    Unauthorized(ProblemDetails),
    /// `forbidden`: only an admin may.
    #[response(status = 403, content_type = "application/problem+json")]
    Forbidden(ProblemDetails),
    /// `unknown-certificate`: none with that thumbprint where it would
    /// have to be, or no OPC UA server with a directory of its own.
    #[response(status = 404, content_type = "application/problem+json")]
    NotFound(ProblemDetails),
    /// `internal`: the files could not be moved or made (the detail says
    /// which and why).
    #[response(status = 500, content_type = "application/problem+json")]
    Failed(ProblemDetails),
}

fn problem(caller: &Caller, e: CertError) -> Problem {
    match e {
        CertError::Refused(refusal) => match refusal.rule {
            Rule::Role { needed, .. } => forbidden(caller, needed),
            _ => Problem::new(Kind::Internal, refusal.detail),
        },
        CertError::Unknown(why) | CertError::Unavailable(why) => {
            Problem::new(Kind::UnknownCertificate, why)
        }
        CertError::Failed(why) => Problem::new(Kind::Internal, why),
    }
}

/// Lists the certificates (admin): the OPC UA server's own, the client
/// applications trusted and refused, user certificates and issuers, and
/// the HTTPS and Modbus/TCP Security ones, each with its subject, issuer,
/// application URI, validity and thumbprints.
#[utoipa::path(
    get,
    path = "/api/v1/certificates",
    tag = "certificates",
    security(("bearer" = ["admin"])),
    responses(
        (status = 200, description = "The certificates", body = CertificatesReply),
        CertificateProblems,
    )
)]
pub async fn list_certificates(
    State(state): State<ApiState>,
    caller: Caller,
) -> Result<Json<CertificatesReply>, Problem> {
    let listing = state
        .control
        .certificates(&caller)
        .await
        .map_err(|e| problem(&caller, e))?;
    let now = SystemTime::now();
    Ok(Json(CertificatesReply {
        certificates: listing
            .certificates
            .iter()
            .map(|h| CertificateView::of(h, now))
            .collect(),
        notes: listing.notes,
    }))
}

async fn act(
    state: &ApiState,
    caller: &Caller,
    action: Action,
) -> Result<Json<CertificateChange>, Problem> {
    let done = state
        .control
        .certificate_action(caller, action)
        .await
        .map_err(|e| problem(caller, e))?;
    let now = SystemTime::now();
    Ok(Json(CertificateChange {
        done: done.words,
        certificate: done
            .certificate
            .as_ref()
            .map(|h| CertificateView::of(h, now)),
    }))
}

/// Trusts a refused OPC UA client application (admin): its certificate
/// moves from `rejected/certs` to `trusted/certs`, and its next
/// connection is accepted, without a restart.
#[utoipa::path(
    post,
    path = "/api/v1/certificates/{thumbprint}/trust",
    tag = "certificates",
    security(("bearer" = ["admin"])),
    params(("thumbprint" = String, Path, description = "The certificate's SHA-1 thumbprint, hex")),
    responses(
        (status = 200, description = "Trusted", body = CertificateChange),
        CertificateProblems,
    )
)]
pub async fn post_trust(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(thumbprint): PathParams<String>,
) -> Result<Json<CertificateChange>, Problem> {
    act(&state, &caller, Action::Trust(thumbprint.to_lowercase())).await
}

/// Removes a trusted OPC UA client application (admin): its certificate
/// moves back to `rejected/certs`; its next connection is refused.
#[utoipa::path(
    delete,
    path = "/api/v1/certificates/{thumbprint}",
    tag = "certificates",
    security(("bearer" = ["admin"])),
    params(("thumbprint" = String, Path, description = "The certificate's SHA-1 thumbprint, hex")),
    responses(
        (status = 200, description = "No longer trusted", body = CertificateChange),
        CertificateProblems,
    )
)]
pub async fn delete_trusted(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(thumbprint): PathParams<String>,
) -> Result<Json<CertificateChange>, Problem> {
    act(&state, &caller, Action::Remove(thumbprint.to_lowercase())).await
}

/// Makes the OPC UA server a new self-signed certificate (admin): the old
/// one is kept beside it, the OPC UA server alone restarts with the new
/// one (its sessions close; clients must trust the new certificate).
#[utoipa::path(
    post,
    path = "/api/v1/certificates/opcua-server/renew",
    operation_id = "post_certificate_renew",
    tag = "certificates",
    security(("bearer" = ["admin"])),
    responses(
        (status = 200, description = "Renewed", body = CertificateChange),
        CertificateProblems,
    )
)]
pub async fn post_renew(
    State(state): State<ApiState>,
    caller: Caller,
) -> Result<Json<CertificateChange>, Problem> {
    act(&state, &caller, Action::Renew).await
}

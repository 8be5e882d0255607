//! Every refusal and failure a face reports, as the API returns it
//! (`application/problem+json`, RFC 9457), and the one place where bus,
//! range and request errors are mapped to their class: the MQTT face
//! publishes the same documents, so a refusal reads the same everywhere.
//! The HTTP response itself (headers, axum's rejections) is `api`'s.
//!
//! Each class of failure has its own `type` and status, so a client can act
//! on it without parsing the text:
//!
//! | type (after `urn:drivegate:problem:`) | status | meaning |
//! |---|---|---|
//! | `invalid-request` | 400 | malformed JSON, wrong types, unknown fields, contradictory fields |
//! | `unauthorized` | 401 | no token, or an unknown one |
//! | `forbidden` | 403 | the token's role does not allow this |
//! | `foreign-origin` | 403 | a browser page from another site tried to change something or open a stream |
//! | `unknown-host` | 421 | the `Host` is not a name drivegate answers to (`[http] allowed_hosts`) |
//! | `too-many-failures` | 429 | too many bad tokens from this address; `Retry-After` says when to retry |
//! | `unknown-drive`, `unknown-bus`, `unknown-command`, `not-found` | 404 | no such thing |
//! | `method-not-allowed` | 405 | the route exists with other methods |
//! | `request-timeout` | 408 | the body did not arrive within `[http] read_timeout_s` |
//! | `payload-too-large` | 413 | body over `[http] max_body_bytes` |
//! | `unsupported-media-type` | 415 | a body that is not `application/json` |
//! | `out-of-range` | 422 | a value outside the manual's range; `valid_range` says which |
//! | `drive-not-active` | 409 | setpoint to a drive that is not activated |
//! | `drive-moving` | 409 | save to flash while the motor turns (send `force`) |
//! | `drive-busy` | 409 | the drive is calibrating or fine-tuning |
//! | `no-lease` | 409 | renewing a lease that is not there (it expired) |
//! | `confirmation-required` | 409 | address setting without `only_drive_on_bus` |
//! | `not-live` | 409 | a command that did not come live from its sender (MQTT: retained, or queued for an earlier session): nothing of it was carried out |
//! | `scope-busy` | 409 | a capture is running on the bus: one at a time |
//! | `capture-not-running` | 409 | trigger or cancel a capture that is over |
//! | `no-capture` | 404 | no capture was armed on the bus since start-up |
//! | `monitor-off` | 409 | `[monitor] enabled = false`: no frames are kept |
//! | `bus-busy` | 429 | the bus queue is full; `Retry-After` says when to retry |
//! | `drive-offline`, `bus-down`, `queue-timeout`, `shutting-down`, `too-many-connections` | 503 | the drive or bus cannot be reached now |
//! | `drive-timeout` | 504 | the drive did not answer |
//! | `drive-refused`, `drive-unconfirmed`, `drive-bad-reply` | 502 | the drive answered with an exception, with something else, or garbage |
//! | `config-invalid` | 422 | a reload's file does not pass the check (`file:line:column`) |
//! | `config-changed`, `no-config-file` | 409 | the file changed since it was read; no file to reload |
//! | `config-edited` | 412 | the file changed since the version `If-Match` names (the detail names the change) |
//! | `if-match-required` | 428 | a change of the file without `If-Match` |
//! | `config-read-only` | 409 | drivegate may not write its configuration file (the new text is not lost: download it) |
//! | `unknown-token`, `unknown-certificate` | 404 | no such token in the file, no certificate with that thumbprint |
//! | `internal` | 500 | a fault of drivegate itself |

use axum::http::StatusCode;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::bus::BusError;
use crate::drive::RangeError;
use crate::listed::listed_enum;
use crate::modbus::ExceptionCode;
use crate::plant::LookupError;

/// Prefix of every problem `type`.
pub const TYPE_PREFIX: &str = "urn:drivegate:problem:";

/// Media type of problem documents.
pub const CONTENT_TYPE: &str = "application/problem+json";

listed_enum! {
    /// The classes of failure, each with its own `type` and status.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
    pub enum Kind {
        /// 400: malformed or contradictory request.
        InvalidRequest,
        /// 401: no token or an unknown one.
        Unauthorized,
        /// 403: the role does not allow it.
        Forbidden,
        /// 403: a state-changing request or a stream from a foreign browser origin.
        ForeignOrigin,
        /// 421: the `Host` is not one the daemon answers to.
        UnknownHost,
        /// 429: too many failed token checks from one address.
        TooManyFailures,
        /// 404: no drive by that name or unit.
        UnknownDrive,
        /// 404: no bus by that name.
        UnknownBus,
        /// 404: no config command by that name.
        UnknownCommand,
        /// 404: no such route.
        NotFound,
        /// 405: the route exists with other methods.
        MethodNotAllowed,
        /// 408: the body came too slowly.
        RequestTimeout,
        /// 413: body too large.
        PayloadTooLarge,
        /// 415: body is not JSON.
        UnsupportedMediaType,
        /// 422: value outside its range.
        OutOfRange,
        /// 409: setpoint to an inactive drive.
        DriveNotActive,
        /// 409: save to flash while moving.
        DriveMoving,
        /// 409: the drive runs a procedure (calibration).
        DriveBusy,
        /// 409: no lease to renew or release.
        NoLease,
        /// 409: a dangerous request lacks its confirmation.
        ConfirmationRequired,
        /// 409: a command that did not come live from its sender.
        NotLive,
        /// 409: a capture is running on the bus.
        ScopeBusy,
        /// 409: the capture is over (or not triggered yet, for some operations).
        CaptureNotRunning,
        /// 404: no capture was armed on the bus.
        NoCapture,
        /// 409: the bus monitor is off.
        MonitorOff,
        /// 422: the configuration file does not pass the check.
        ConfigInvalid,
        /// 409: the configuration file changed on disk since it was read.
        ConfigChanged,
        /// 409: there is no configuration file to reload.
        NoConfigFile,
        /// 412: the configuration file changed since the `If-Match` version.
        ConfigEdited,
        /// 428: a change of the configuration file needs `If-Match`.
        IfMatchRequired,
        /// 409: the daemon may not write its configuration file.
        ConfigReadOnly,
        /// 404: no API token by that name in the file.
        UnknownToken,
        /// 404: no certificate with that thumbprint.
        UnknownCertificate,
        /// 429: bus queue full.
        BusBusy,
        /// 503: drive offline.
        DriveOffline,
        /// 503: serial port down.
        BusDown,
        /// 503: waited too long for the bus.
        QueueTimeout,
        /// 503: the daemon is stopping.
        ShuttingDown,
        /// 503: connection limit reached.
        TooManyConnections,
        /// 504: the drive did not answer.
        DriveTimeout,
        /// 502: the drive answered with a Modbus exception.
        DriveRefused,
        /// 502: the drive answered, but not with a confirmation of this request.
        DriveUnconfirmed,
        /// 502: only corrupted replies.
        DriveBadReply,
        /// 500: a fault of drivegate itself.
        Internal,
    }
}

impl Kind {
    /// The last part of the `type` URI.
    pub const fn slug(self) -> &'static str {
        match self {
            Kind::InvalidRequest => "invalid-request",
            Kind::Unauthorized => "unauthorized",
            Kind::Forbidden => "forbidden",
            Kind::ForeignOrigin => "foreign-origin",
            Kind::UnknownHost => "unknown-host",
            Kind::TooManyFailures => "too-many-failures",
            Kind::UnknownDrive => "unknown-drive",
            Kind::UnknownBus => "unknown-bus",
            Kind::UnknownCommand => "unknown-command",
            Kind::NotFound => "not-found",
            Kind::MethodNotAllowed => "method-not-allowed",
            Kind::RequestTimeout => "request-timeout",
            Kind::PayloadTooLarge => "payload-too-large",
            Kind::UnsupportedMediaType => "unsupported-media-type",
            Kind::OutOfRange => "out-of-range",
            Kind::DriveNotActive => "drive-not-active",
            Kind::DriveMoving => "drive-moving",
            Kind::DriveBusy => "drive-busy",
            Kind::NoLease => "no-lease",
            Kind::ConfirmationRequired => "confirmation-required",
            Kind::NotLive => "not-live",
            Kind::ScopeBusy => "scope-busy",
            Kind::CaptureNotRunning => "capture-not-running",
            Kind::NoCapture => "no-capture",
            Kind::MonitorOff => "monitor-off",
            Kind::ConfigInvalid => "config-invalid",
            Kind::ConfigChanged => "config-changed",
            Kind::NoConfigFile => "no-config-file",
            Kind::ConfigEdited => "config-edited",
            Kind::IfMatchRequired => "if-match-required",
            Kind::ConfigReadOnly => "config-read-only",
            Kind::UnknownToken => "unknown-token",
            Kind::UnknownCertificate => "unknown-certificate",
            Kind::BusBusy => "bus-busy",
            Kind::DriveOffline => "drive-offline",
            Kind::BusDown => "bus-down",
            Kind::QueueTimeout => "queue-timeout",
            Kind::ShuttingDown => "shutting-down",
            Kind::TooManyConnections => "too-many-connections",
            Kind::DriveTimeout => "drive-timeout",
            Kind::DriveRefused => "drive-refused",
            Kind::DriveUnconfirmed => "drive-unconfirmed",
            Kind::DriveBadReply => "drive-bad-reply",
            Kind::Internal => "internal",
        }
    }

    /// The kind whose [`slug`](Self::slug) is `slug`.
    pub fn from_slug(slug: &str) -> Option<Kind> {
        Kind::ALL.into_iter().find(|k| k.slug() == slug)
    }

    /// The HTTP status of this kind.
    pub const fn status(self) -> StatusCode {
        match self {
            Kind::InvalidRequest => StatusCode::BAD_REQUEST,
            Kind::Unauthorized => StatusCode::UNAUTHORIZED,
            Kind::Forbidden | Kind::ForeignOrigin => StatusCode::FORBIDDEN,
            Kind::UnknownHost => StatusCode::MISDIRECTED_REQUEST,
            Kind::TooManyFailures => StatusCode::TOO_MANY_REQUESTS,
            Kind::UnknownDrive
            | Kind::UnknownBus
            | Kind::UnknownCommand
            | Kind::NotFound
            | Kind::NoCapture
            | Kind::UnknownToken
            | Kind::UnknownCertificate => StatusCode::NOT_FOUND,
            Kind::MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
            Kind::RequestTimeout => StatusCode::REQUEST_TIMEOUT,
            Kind::PayloadTooLarge => StatusCode::PAYLOAD_TOO_LARGE,
            Kind::UnsupportedMediaType => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            Kind::OutOfRange => StatusCode::UNPROCESSABLE_ENTITY,
            Kind::DriveNotActive
            | Kind::DriveMoving
            | Kind::DriveBusy
            | Kind::NoLease
            | Kind::ConfirmationRequired
            | Kind::NotLive
            | Kind::ScopeBusy
            | Kind::CaptureNotRunning
            | Kind::MonitorOff
            | Kind::ConfigChanged
            | Kind::ConfigReadOnly
            | Kind::NoConfigFile => StatusCode::CONFLICT,
            Kind::ConfigEdited => StatusCode::PRECONDITION_FAILED,
            Kind::IfMatchRequired => StatusCode::PRECONDITION_REQUIRED,
            Kind::ConfigInvalid => StatusCode::UNPROCESSABLE_ENTITY,
            Kind::BusBusy => StatusCode::TOO_MANY_REQUESTS,
            Kind::DriveOffline
            | Kind::BusDown
            | Kind::QueueTimeout
            | Kind::ShuttingDown
            | Kind::TooManyConnections => StatusCode::SERVICE_UNAVAILABLE,
            Kind::DriveTimeout => StatusCode::GATEWAY_TIMEOUT,
            Kind::DriveRefused | Kind::DriveUnconfirmed | Kind::DriveBadReply => {
                StatusCode::BAD_GATEWAY
            }
            Kind::Internal => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    /// Short summary, the same for every occurrence.
    pub const fn title(self) -> &'static str {
        match self {
            Kind::InvalidRequest => "The request is malformed",
            Kind::Unauthorized => "A valid API token is required",
            Kind::Forbidden => "The token's role does not allow this",
            Kind::ForeignOrigin => "Requests from another site's page are refused",
            Kind::UnknownHost => "drivegate does not answer to this host name",
            Kind::TooManyFailures => "Too many invalid tokens from this address",
            Kind::UnknownDrive => "No such drive",
            Kind::UnknownBus => "No such bus",
            Kind::UnknownCommand => "No such command",
            Kind::NotFound => "No such resource",
            Kind::MethodNotAllowed => "Method not allowed here",
            Kind::RequestTimeout => "The request body did not arrive in time",
            Kind::PayloadTooLarge => "The request body is too large",
            Kind::UnsupportedMediaType => "The request body must be JSON",
            Kind::OutOfRange => "A value is out of range",
            Kind::DriveNotActive => "The drive is not active",
            Kind::DriveMoving => "The motor is moving",
            Kind::DriveBusy => "The drive is busy with a procedure",
            Kind::NoLease => "There is no lease",
            Kind::ConfirmationRequired => "A confirmation is required",
            Kind::NotLive => "The command did not come live from its sender",
            Kind::ScopeBusy => "A capture is running on this bus",
            Kind::CaptureNotRunning => "The capture is not running",
            Kind::NoCapture => "No capture yet",
            Kind::MonitorOff => "The bus monitor is off",
            Kind::ConfigInvalid => "The configuration file does not pass the check",
            Kind::ConfigChanged => "The configuration file changed since it was read",
            Kind::NoConfigFile => "There is no configuration file to reload",
            Kind::ConfigEdited => "The configuration file was changed by someone else",
            Kind::IfMatchRequired => "Say which version of the file the change is made on",
            Kind::ConfigReadOnly => "drivegate may not write its configuration file",
            Kind::UnknownToken => "No such API token",
            Kind::UnknownCertificate => "No such certificate",
            Kind::BusBusy => "The bus is busy",
            Kind::DriveOffline => "The drive is offline",
            Kind::BusDown => "The bus is down",
            Kind::QueueTimeout => "The bus did not take the request in time",
            Kind::ShuttingDown => "The daemon is shutting down",
            Kind::TooManyConnections => "Too many connections",
            Kind::DriveTimeout => "The drive did not answer",
            Kind::DriveRefused => "The drive refused the request",
            Kind::DriveUnconfirmed => "The drive did not confirm the request",
            Kind::DriveBadReply => "The drive's replies were corrupted",
            Kind::Internal => "Internal error",
        }
    }

    /// The full `type` URI.
    pub fn type_uri(self) -> String {
        format!("{TYPE_PREFIX}{}", self.slug())
    }
}

/// The range a value must be in, in the unit of the request.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct ValidRange {
    /// Lowest accepted value.
    pub min: f64,
    /// Highest accepted value.
    pub max: f64,
    /// Unit of `min` and `max` ("rpm", "deg", "A", "counts", "ms", "s"; may be empty).
    pub unit: String,
}

/// An RFC 9457 problem document ("problem details").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct ProblemDetails {
    /// `urn:drivegate:problem:<class>`: what went wrong, for programs.
    #[serde(rename = "type")]
    pub type_uri: String,
    /// Summary of the class.
    pub title: String,
    /// The HTTP status.
    pub status: u16,
    /// What happened in this case and what to do about it.
    pub detail: String,
    /// For `out-of-range`: the accepted range.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub valid_range: Option<ValidRange>,
    /// The drive concerned, when there is one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub drive: Option<String>,
    /// For `drive-refused`: the Modbus exception code the drive sent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exception_code: Option<u8>,
    /// Seconds after which a retry makes sense (also sent as `Retry-After`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub retry_after_s: Option<u64>,
    /// For a settings document refused whole: every value refused, each
    /// with its valid range.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub invalid_settings: Vec<InvalidSetting>,
    /// For a settings document that failed part-way: what became of each
    /// setting (the `SettingsDiff` of a success, `complete` false).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Object>)]
    pub settings_report: Option<serde_json::Value>,
}

/// A value of a settings document that was refused.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct InvalidSetting {
    /// Its path in the document (`protection.stall_ms`).
    pub setting: String,
    /// What is wrong.
    pub detail: String,
    /// Its valid range, when it is out of range.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub valid_range: Option<ValidRange>,
}

/// The error every handler returns: its [`Kind`] and a boxed
/// [`ProblemDetails`], small to pass around (errors are the cold path) and
/// serialised as the document. The kind is kept as a type: the document's
/// `type` is only read back for a document that came from elsewhere.
#[derive(Debug, Clone, PartialEq)]
pub struct Problem {
    kind: Kind,
    details: Box<ProblemDetails>,
}

impl std::ops::Deref for Problem {
    type Target = ProblemDetails;

    fn deref(&self) -> &ProblemDetails {
        &self.details
    }
}

impl std::ops::DerefMut for Problem {
    fn deref_mut(&mut self) -> &mut ProblemDetails {
        &mut self.details
    }
}

impl Serialize for Problem {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        self.details.serialize(serializer)
    }
}

impl<'de> Deserialize<'de> for Problem {
    /// A document received (a client's view): its kind from its `type`,
    /// [`Kind::Internal`] for a `type` drivegate does not send.
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let details = ProblemDetails::deserialize(deserializer)?;
        let kind = details
            .type_uri
            .strip_prefix(TYPE_PREFIX)
            .and_then(Kind::from_slug)
            .unwrap_or(Kind::Internal);
        Ok(Problem {
            kind,
            details: Box::new(details),
        })
    }
}

/// What the mapping of a bus error needs to know about the request.
#[derive(Debug, Clone, Copy, Default)]
pub struct BusContext<'a> {
    /// The drive's name.
    pub drive: Option<&'a str>,
    /// True when the drive was offline before the request: a timeout then
    /// means "still offline", not "slow".
    pub offline: bool,
    /// True for speed/position/torque setpoints: the drive answers them
    /// with exception 0x04 when it is not active.
    pub setpoint: bool,
}

impl Problem {
    /// A problem of `kind` with `detail`.
    pub fn new(kind: Kind, detail: impl Into<String>) -> Self {
        let details = Box::new(ProblemDetails {
            type_uri: kind.type_uri(),
            title: kind.title().to_string(),
            status: kind.status().as_u16(),
            detail: detail.into(),
            valid_range: None,
            drive: None,
            exception_code: None,
            retry_after_s: None,
            invalid_settings: Vec::new(),
            settings_report: None,
        });
        Problem { kind, details }
    }

    /// The document.
    pub fn details(&self) -> &ProblemDetails {
        &self.details
    }

    /// Names the drive concerned.
    pub fn for_drive(mut self, drive: &str) -> Self {
        self.drive = Some(drive.to_string());
        self
    }

    /// Asks the client to wait `seconds` before retrying.
    pub fn retry_after(mut self, seconds: u64) -> Self {
        self.retry_after_s = Some(seconds);
        self
    }

    /// The class.
    pub fn kind(&self) -> Kind {
        self.kind
    }

    /// 400 with `detail`.
    pub fn invalid(detail: impl Into<String>) -> Self {
        Problem::new(Kind::InvalidRequest, detail)
    }

    /// 422 naming the range.
    pub fn range(err: &RangeError) -> Self {
        let mut p = Problem::new(Kind::OutOfRange, err.to_string());
        p.valid_range = Some(ValidRange {
            min: err.min,
            max: err.max,
            unit: err.unit.to_string(),
        });
        p
    }

    /// 404 for a drive that cannot be found.
    pub fn lookup(err: &LookupError) -> Self {
        Problem::new(Kind::UnknownDrive, err.to_string())
    }

    /// The problem for a bus error of a request to a drive.
    pub fn bus(err: &BusError, ctx: BusContext<'_>) -> Self {
        let mut p = match err {
            BusError::Busy { .. } => Problem::new(Kind::BusBusy, err.to_string()).retry_after(1),
            BusError::BusDown { .. } => Problem::new(
                Kind::BusDown,
                format!("{err}; drivegate reopens the port by itself"),
            )
            .retry_after(5),
            BusError::Timeout { .. } if ctx.offline => Problem::new(
                Kind::DriveOffline,
                format!(
                    "the drive is offline (it stopped answering its status polls) and did not answer this request either: {err}; check its power and wiring"
                ),
            )
            .retry_after(5),
            BusError::Timeout { .. } => Problem::new(
                Kind::DriveTimeout,
                format!("{err}; whether the drive carried the request out is unknown"),
            ),
            BusError::BusDownAfterSend { .. } => Problem::new(Kind::DriveTimeout, err.to_string()),
            BusError::BadReply { .. } => Problem::new(
                Kind::DriveBadReply,
                format!(
                    "{err}; whether the drive carried the request out is unknown: check the wiring, termination and shield"
                ),
            ),
            BusError::Exception { code, .. } => exception(err, *code, ctx),
            BusError::Unconfirmed { .. } => Problem::new(
                Kind::DriveUnconfirmed,
                format!("{err}; whether the drive carried the request out is unknown"),
            ),
            BusError::Expired { .. } => {
                Problem::new(Kind::QueueTimeout, err.to_string()).retry_after(1)
            }
            BusError::ShuttingDown => Problem::new(Kind::ShuttingDown, err.to_string()),
            BusError::Invalid(_) => Problem::new(Kind::Internal, err.to_string()),
        };
        if let Some(drive) = ctx.drive {
            p.drive = Some(drive.to_string());
        }
        p
    }

    /// The HTTP status.
    pub fn status_code(&self) -> StatusCode {
        StatusCode::from_u16(self.status).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR)
    }
}

fn exception(err: &BusError, code: ExceptionCode, ctx: BusContext<'_>) -> Problem {
    let mut p = if code == ExceptionCode::SERVER_DEVICE_FAILURE && ctx.setpoint {
        Problem::new(
            Kind::DriveNotActive,
            format!(
                "{err}: the drive takes setpoints only when active; send the activate command first"
            ),
        )
    } else if code == ExceptionCode::SERVER_DEVICE_BUSY {
        Problem::new(
            Kind::DriveBusy,
            format!("{err}: the drive is running a procedure (calibration takes about 4 s); try again when it is done"),
        )
        .retry_after(1)
    } else {
        Problem::new(Kind::DriveRefused, err.to_string())
    };
    p.exception_code = Some(code.0);
    p
}

impl std::fmt::Display for Problem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({}): {}", self.title, self.status, self.detail)
    }
}

impl std::error::Error for Problem {}

impl From<RangeError> for Problem {
    fn from(err: RangeError) -> Self {
        Problem::range(&err)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_round_trips_through_its_type() {
        for kind in Kind::ALL {
            let p = Problem::new(kind, "x");
            assert_eq!(p.kind(), kind);
            assert_eq!(p.status, kind.status().as_u16());
        }
        let mut slugs: Vec<_> = Kind::ALL.iter().map(|k| k.slug()).collect();
        slugs.sort_unstable();
        slugs.dedup();
        assert_eq!(slugs.len(), Kind::ALL.len());
    }

    #[test]
    fn bus_errors_map_to_their_own_classes() {
        let ctx = BusContext::default();
        let busy = BusError::Busy {
            bus: "b".into(),
            priority: crate::bus::Priority::Command,
            capacity: 4,
        };
        let p = Problem::bus(&busy, ctx);
        assert_eq!(
            (p.kind(), p.status, p.retry_after_s),
            (Kind::BusBusy, 429, Some(1))
        );
        let timeout = BusError::Timeout {
            unit: 1,
            attempts: 2,
            timeout_ms: 50,
        };
        assert_eq!(Problem::bus(&timeout, ctx).kind(), Kind::DriveTimeout);
        let offline = BusContext {
            offline: true,
            ..ctx
        };
        assert_eq!(Problem::bus(&timeout, offline).status, 503);
        let refused = BusError::Exception {
            unit: 1,
            code: ExceptionCode::SERVER_DEVICE_FAILURE,
        };
        let p = Problem::bus(&refused, ctx);
        assert_eq!((p.kind(), p.exception_code), (Kind::DriveRefused, Some(4)));
        let setpoint = BusContext {
            setpoint: true,
            drive: Some("conveyor"),
            ..ctx
        };
        let p = Problem::bus(&refused, setpoint);
        assert_eq!((p.kind(), p.status), (Kind::DriveNotActive, 409));
        assert_eq!(p.drive.as_deref(), Some("conveyor"));
        let busy_drive = BusError::Exception {
            unit: 1,
            code: ExceptionCode::SERVER_DEVICE_BUSY,
        };
        assert_eq!(Problem::bus(&busy_drive, ctx).kind(), Kind::DriveBusy);
    }

    #[test]
    fn range_errors_carry_the_range() {
        let err = crate::drive::units::speed_setpoint(3000.0).unwrap_err();
        let p = Problem::from(err);
        assert_eq!(p.status, 422);
        let r = p.valid_range.clone().unwrap();
        assert_eq!((r.min, r.max, r.unit.as_str()), (-2048.0, 2047.0, "rpm"));
    }
}

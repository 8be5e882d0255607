//! The core's answers as OPC UA status codes, with the core's own words as
//! the diagnostic text (a client that asks for diagnostics, e.g.
//! `returnDiagnostics = 0x3FF`, gets them in `AdditionalInfo`). Pure.
//!
//! | refused because | status code |
//! |---|---|
//! | the session's role does not allow it | `BadUserAccessDenied` |
//! | a value outside the drive's range (the range in the text) | `BadOutOfRange` |
//! | a still-check: the motor turns; a setpoint to a drive that is not active | `BadInvalidState` |
//! | a write the core cannot decode | `BadNotSupported` |
//! | the bus is down, the drive does not answer | `BadNoCommunication`, `BadTimeout` |
//! | the bus queue is full, or the request waited too long | `BadResourceUnavailable` |
//! | the drive refused it (its Modbus exception) | `BadDeviceFailure` |
//! | sent, but not confirmed: it may have been carried out | `BadTimeout` ("may have been carried out") |

use opcua::types::{DiagnosticInfo, StatusCode, UAString};

use crate::bus::BusError;
use crate::control::{Failure, Rule};
use crate::drive::RangeError;

/// A refusal or failure: its status code and its words.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Answer {
    /// The status code of the operation.
    pub status: StatusCode,
    /// What happened and what to do, for the diagnostics.
    pub text: String,
}

impl Answer {
    /// An answer with `status` and `text`.
    pub fn new(status: StatusCode, text: impl Into<String>) -> Self {
        Answer {
            status,
            text: text.into(),
        }
    }

    /// The text as a diagnostic info.
    pub fn diagnostic(&self) -> DiagnosticInfo {
        DiagnosticInfo {
            additional_info: Some(UAString::from(self.text.as_str())),
            ..Default::default()
        }
    }
}

/// A value outside the drive's range.
pub fn out_of_range(e: &RangeError) -> Answer {
    Answer::new(StatusCode::BadOutOfRange, e.to_string())
}

/// What a failed write comes to.
pub fn failure(failure: &Failure) -> Answer {
    let status = match failure {
        Failure::Refused(refusal) => match refusal.rule {
            Rule::Role { .. } => StatusCode::BadUserAccessDenied,
            Rule::Moving { .. } | Rule::NotActive | Rule::SharedBusAddress => {
                StatusCode::BadInvalidState
            }
            Rule::LeaseLength { .. } => StatusCode::BadOutOfRange,
            Rule::NotDecoded => StatusCode::BadNotSupported,
            Rule::NotLive => StatusCode::BadRequestTimeout,
        },
        Failure::CheckFailed(e) | Failure::NotSent(e) => bus_status(e),
        Failure::DriveRefused { .. } => StatusCode::BadDeviceFailure,
        Failure::Unknown { .. } => StatusCode::BadTimeout,
    };
    let text = match failure {
        Failure::Refused(refusal) => refusal.detail.clone(),
        Failure::Unknown { .. } => format!(
            "{failure}: the drive may have carried it out; read its status before trying again"
        ),
        other => other.to_string(),
    };
    Answer::new(status, text)
}

/// The status code of a bus error.
pub fn bus_status(error: &BusError) -> StatusCode {
    match error {
        BusError::BusDown { .. } | BusError::ShuttingDown => StatusCode::BadNoCommunication,
        BusError::Busy { .. } | BusError::Expired { .. } => StatusCode::BadResourceUnavailable,
        BusError::Timeout { .. }
        | BusError::BadReply { .. }
        | BusError::BusDownAfterSend { .. } => StatusCode::BadTimeout,
        BusError::Exception { .. } | BusError::Unconfirmed { .. } => StatusCode::BadDeviceFailure,
        BusError::Invalid(_) => StatusCode::BadInvalidArgument,
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;
    use crate::control::policy::StillReason;
    use crate::control::{Refusal, Role};

    fn refused(rule: Rule) -> Failure {
        Failure::Refused(Refusal {
            rule,
            detail: "the core's words".into(),
        })
    }

    #[test]
    fn each_rule_has_its_status_code_and_the_cores_words() {
        let cases = [
            (
                refused(Rule::Role {
                    needed: Role::Operator,
                    has: Role::Viewer,
                }),
                StatusCode::BadUserAccessDenied,
            ),
            (
                refused(Rule::Moving {
                    still: StillReason::Save,
                    speed_rpm: 300,
                }),
                StatusCode::BadInvalidState,
            ),
            (refused(Rule::NotActive), StatusCode::BadInvalidState),
            (refused(Rule::NotDecoded), StatusCode::BadNotSupported),
        ];
        for (f, status) in cases {
            let a = failure(&f);
            assert_eq!(a.status, status, "{f:?}");
            assert_eq!(a.text, "the core's words");
            assert_eq!(
                a.diagnostic().additional_info,
                Some(UAString::from("the core's words"))
            );
        }
    }

    #[test]
    fn bus_failures_say_whether_the_drive_may_have_done_it() {
        let down = Failure::NotSent(BusError::BusDown {
            bus: "line1".into(),
            reason: "unplugged".to_string().into(),
        });
        assert_eq!(failure(&down).status, StatusCode::BadNoCommunication);
        let busy = Failure::NotSent(BusError::Expired {
            waited: Duration::from_secs(1),
        });
        assert_eq!(failure(&busy).status, StatusCode::BadResourceUnavailable);
        let unknown = Failure::Unknown {
            error: BusError::Timeout {
                unit: 1,
                attempts: 2,
                timeout_ms: 50,
            },
            reply: None,
        };
        let a = failure(&unknown);
        assert_eq!(a.status, StatusCode::BadTimeout);
        assert!(a.text.contains("may have carried it out"), "{}", a.text);
        let range = crate::drive::units::speed_setpoint(99_999.0).unwrap_err();
        let a = out_of_range(&range);
        assert_eq!(a.status, StatusCode::BadOutOfRange);
        assert!(
            a.text.contains("-2048") && a.text.contains("2047"),
            "{}",
            a.text
        );
    }
}

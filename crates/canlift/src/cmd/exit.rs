//! Exit statuses of the operator commands (`lifts`, `get`, `put`, `watch`, `token`, `alarms`,
//! `events`; docs/PORTAL.md §Command-line client): a script tells a missing lift, a refused key, a
//! lift that said no and a portal it cannot reach apart without reading the message.

use std::process::ExitCode;

use nxg::msg::ErrorObject;

/// Why an operator command failed, as its exit status says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Failure {
    /// 3: no such lift, object or alarm (404).
    NotFound = 3,
    /// 4: the key is unknown, or its role may not do this (401, 403 of the portal).
    NotAllowed = 4,
    /// 5: the lift refused (its gateway's NXg error: an abort code, a privilege, a hash).
    RefusedByLift = 5,
    /// 6: the portal cannot be reached, or the lift is offline or did not answer (503, 504).
    Unreachable = 6,
    /// 7: too many requests: try again later (429).
    Busy = 7,
}

/// An answer of the portal other than 2xx, with the exit status it means.
#[derive(Debug, thiserror::Error)]
#[error("{status}: {message}")]
pub struct Refused {
    /// The HTTP status.
    pub status: u16,
    /// The portal's or the gateway's message.
    pub message: String,
    /// What it means.
    pub failure: Option<Failure>,
}

impl Refused {
    /// The portal answered `status` with `body`. The portal's own errors carry the HTTP status
    /// as their code; a lift's refusal carries the gateway's NXg code.
    pub fn of(status: u16, body: &serde_json::Value) -> Refused {
        let error = serde_json::from_value::<ErrorObject>(body.clone()).ok();
        let from_lift = error.as_ref().is_some_and(|e| e.code != i64::from(status));
        let failure = match status {
            _ if from_lift => Some(Failure::RefusedByLift),
            404 => Some(Failure::NotFound),
            401 | 403 => Some(Failure::NotAllowed),
            429 => Some(Failure::Busy),
            503 | 504 => Some(Failure::Unreachable),
            _ => None,
        };
        Refused {
            status,
            message: error.map_or_else(|| body.to_string(), |e| e.to_string()),
            failure,
        }
    }
}

/// The exit status of a command that ended with `e`: 1 unless it is one of [`Failure`].
pub fn status(e: &anyhow::Error) -> ExitCode {
    let failure = e.chain().find_map(|cause| {
        if let Some(refused) = cause.downcast_ref::<Refused>() {
            return refused.failure;
        }
        cause
            .downcast_ref::<cloud::client::ClientError>()
            .map(|_| Failure::Unreachable)
    });
    failure.map_or(ExitCode::FAILURE, |f| ExitCode::from(f as u8))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn answers_mean_exit_statuses() {
        let of = |status, body| Refused::of(status, &body).failure;
        assert_eq!(
            of(404, json!({"code": 404, "message": "no such lift"})),
            Some(Failure::NotFound)
        );
        assert_eq!(
            of(403, json!({"code": 403, "message": "a viewer"})),
            Some(Failure::NotAllowed)
        );
        // The gateway's privilege refusal (NXg) also comes as 403: the lift said no.
        assert_eq!(
            of(403, json!({"code": 134217761, "message": "privilege"})),
            Some(Failure::RefusedByLift)
        );
        assert_eq!(
            of(504, json!({"code": 504, "message": "no answer"})),
            Some(Failure::Unreachable)
        );
        assert_eq!(
            of(429, json!({"code": 429, "message": "slow down"})),
            Some(Failure::Busy)
        );
        assert_eq!(of(500, json!("boom")), None);
        let e = anyhow::Error::new(Refused::of(404, &json!({"code": 404, "message": "x"})))
            .context("reading 0x652001");
        assert_eq!(status(&e), ExitCode::from(3));
        let unreachable = anyhow::Error::new(cloud::client::ClientError::Io("refused".into()));
        assert_eq!(status(&unreachable), ExitCode::from(6));
        assert_eq!(status(&anyhow::anyhow!("other")), ExitCode::FAILURE);
    }
}

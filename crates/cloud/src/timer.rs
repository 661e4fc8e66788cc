//! The timer arm of a driver's `select!` over a sans-IO core's next deadline.

/// Sleep until `deadline`, or forever without one.
pub(crate) async fn sleep_until(deadline: Option<impl Into<tokio::time::Instant>>) {
    match deadline {
        Some(d) => tokio::time::sleep_until(d.into()).await,
        None => std::future::pending().await,
    }
}

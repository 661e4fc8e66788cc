//! A request's small body read before the request is routed (docs/SECURITY.md §Bounds), so that
//! a refusal that never looks at the body (405, 401, 415, 429, …) leaves the connection usable.
//!
//! hyper keeps an HTTP/1.1 connection open after an answer only if the request's body was read
//! to its end, or is in its buffer when the answer is written; otherwise it closes the
//! connection just after the answer. A client (Python's `http.client` sends a body after its
//! head, in a record of its own) that has the answer and sends its next request on the same
//! connection before the close reaches it loses that request: "Remote end closed connection
//! without response" (RFC 9112 §9.3.1 lets it retry only idempotent ones). A busy portal makes
//! that window wider. Reading the body first shuts it: the connection closes only when the
//! body is not worth reading (larger than [`READ_FIRST`] or chunked, both of which no operation
//! of the API or the web UI takes) or does not come.

use axum::body::{Body, Bytes};
use axum::extract::Request;
use axum::http::{header, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

/// The largest body read before the request is routed. Every JSON body and form the portal
/// takes is smaller (the largest, a write of many objects, is a few KiB); reading it costs no
/// more than hyper's own buffer holds, before the caller is known.
pub const READ_FIRST: usize = 64 * 1024;

/// How long a body read first may take to arrive once its head has: a client that sends its
/// head and then its body slowly, or never, is answered 408 and the connection closed, like one
/// slow with its head (`connection::HEAD_TIMEOUT`).
pub const BODY_TIMEOUT: std::time::Duration = crate::connection::HEAD_TIMEOUT;

/// The middleware: read a body of a declared length up to [`READ_FIRST`], then route the
/// request with it; pass any other on as it is.
pub async fn read_first(request: Request, next: Next) -> Response {
    let declared = request
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<usize>().ok());
    let Some(length @ 1..=READ_FIRST) = declared else {
        return next.run(request).await;
    };
    let (parts, body) = request.into_parts();
    match tokio::time::timeout(BODY_TIMEOUT, axum::body::to_bytes(body, length)).await {
        Ok(Ok(bytes)) => {
            next.run(Request::from_parts(parts, Body::from(bytes)))
                .await
        }
        // Fewer bytes than declared before the client closed, or a broken connection.
        Ok(Err(_)) => closing(StatusCode::BAD_REQUEST, "the request's body is cut short"),
        Err(_) => closing(
            StatusCode::REQUEST_TIMEOUT,
            "the request's body did not arrive in time",
        ),
    }
}

/// An answer after which the connection closes: what is left of its request cannot be told
/// from the next one.
fn closing(status: StatusCode, why: &'static str) -> Response {
    let mut response = (status, Bytes::from_static(why.as_bytes())).into_response();
    response
        .headers_mut()
        .insert(header::CONNECTION, HeaderValue::from_static("close"));
    response
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::routing::post;
    use axum::Router;
    use http_body_util::BodyExt;
    use tower::ServiceExt;

    /// The body a handler sees is the one sent, whole, whether read first or passed on.
    #[tokio::test]
    async fn handlers_get_the_body_as_sent() {
        let app = Router::new()
            .route("/", post(|body: Bytes| async move { body }))
            .layer(axum::middleware::from_fn(read_first));
        for size in [1, 1000, READ_FIRST, READ_FIRST + 1] {
            let sent: Vec<u8> = (0..size).map(|i| (i % 251) as u8).collect();
            let request = Request::post("/")
                .header(header::CONTENT_LENGTH, size)
                .body(Body::from(sent.clone()))
                .unwrap();
            let response = app.clone().oneshot(request).await.unwrap();
            assert_eq!(response.status(), StatusCode::OK, "{size} bytes");
            let got = response.into_body().collect().await.unwrap().to_bytes();
            assert_eq!(got, sent, "{size} bytes");
        }
    }

    /// A body shorter than declared is refused with the connection closed; one that never
    /// comes is refused after [`BODY_TIMEOUT`].
    #[tokio::test(start_paused = true)]
    async fn a_body_cut_short_or_late_is_refused_and_closes() {
        let app = Router::new()
            .route("/", post(|| async { "reached" }))
            .layer(axum::middleware::from_fn(read_first));
        // What hyper's body yields when the client closes before its declared length.
        let cut = futures_util::stream::iter([
            Ok(Bytes::from_static(b"12345")),
            Err(std::io::Error::from(std::io::ErrorKind::UnexpectedEof)),
        ]);
        let short = Request::post("/")
            .header(header::CONTENT_LENGTH, 10)
            .body(Body::from_stream(cut))
            .unwrap();
        let response = app.clone().oneshot(short).await.unwrap();
        assert_eq!(response.status(), StatusCode::BAD_REQUEST);
        assert_eq!(response.headers()[header::CONNECTION], "close");

        let body =
            Body::from_stream(futures_util::stream::pending::<Result<Bytes, std::io::Error>>());
        let late = Request::post("/")
            .header(header::CONTENT_LENGTH, 10)
            .body(body)
            .unwrap();
        let began = tokio::time::Instant::now();
        let response = app.oneshot(late).await.unwrap();
        assert_eq!(response.status(), StatusCode::REQUEST_TIMEOUT);
        assert_eq!(response.headers()[header::CONNECTION], "close");
        assert_eq!(began.elapsed(), BODY_TIMEOUT);
    }
}

//! The UI's static files: served under content-hashed names (`/static/app.1a2b3c4d5e6f7a8b.js`)
//! with a year of immutable caching, so a browser fetches each version once and a new release
//! is picked up at once; the plain names answer too (revalidated each time). Every answer has
//! an ETag and `If-None-Match` gets 304.

use std::sync::LazyLock;

use axum::extract::Path;
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};

/// One static file.
struct Asset {
    /// Its plain name, e.g. `app.js`.
    name: &'static str,
    /// Its content type.
    kind: &'static str,
    body: &'static str,
    /// The content-hashed name, e.g. `app.1a2b3c4d5e6f7a8b.js`.
    hashed: String,
    /// The ETag (quoted hash).
    etag: String,
}

impl Asset {
    fn new(name: &'static str, kind: &'static str, body: &'static str) -> Self {
        let digest = ring::digest::digest(&ring::digest::SHA256, body.as_bytes());
        let hash: String = digest.as_ref()[..8]
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        let (stem, ext) = name.rsplit_once('.').unwrap_or((name, ""));
        Asset {
            name,
            kind,
            body,
            hashed: format!("{stem}.{hash}.{ext}"),
            etag: format!("\"{hash}\""),
        }
    }
}

static ASSETS: LazyLock<[Asset; 3]> = LazyLock::new(|| {
    [
        Asset::new(
            "app.js",
            "text/javascript; charset=utf-8",
            include_str!("app.js"),
        ),
        Asset::new(
            "style.css",
            "text/css; charset=utf-8",
            include_str!("style.css"),
        ),
        Asset::new("favicon.svg", "image/svg+xml", include_str!("favicon.svg")),
    ]
});

/// The URL a page links `name` (`app.js`, `style.css`, `favicon.svg`) by.
pub(super) fn url(name: &str) -> String {
    match ASSETS.iter().find(|a| a.name == name) {
        Some(a) => format!("/static/{}", a.hashed),
        None => format!("/static/{name}"),
    }
}

/// `GET /static/{file}`.
pub(super) async fn serve(Path(file): Path<String>, headers: HeaderMap) -> Response {
    let Some(asset) = ASSETS.iter().find(|a| a.hashed == file || a.name == file) else {
        return StatusCode::NOT_FOUND.into_response();
    };
    let immutable = asset.hashed == file;
    answer(asset, &headers, immutable)
}

/// `GET /favicon.ico`: browsers ask for it whatever the page links.
pub(super) async fn favicon(headers: HeaderMap) -> Response {
    let icon = ASSETS.iter().find(|a| a.name == "favicon.svg");
    match icon {
        Some(asset) => answer(asset, &headers, false),
        None => StatusCode::NOT_FOUND.into_response(),
    }
}

fn answer(asset: &Asset, headers: &HeaderMap, immutable: bool) -> Response {
    let cache = if immutable {
        "public, max-age=31536000, immutable"
    } else {
        "no-cache"
    };
    let fresh = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|tags| tags.split(',').any(|t| t.trim() == asset.etag));
    let common = [
        (header::CACHE_CONTROL, cache.to_owned()),
        (header::ETAG, asset.etag.clone()),
    ];
    if fresh {
        return (StatusCode::NOT_MODIFIED, common).into_response();
    }
    (
        common,
        [(header::CONTENT_TYPE, asset.kind.to_owned())],
        asset.body,
    )
        .into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hashed_names_follow_the_content() {
        let app = url("app.js");
        assert!(
            app.starts_with("/static/app.") && app.ends_with(".js"),
            "{app}"
        );
        assert_eq!(app.len(), "/static/app.".len() + 16 + ".js".len());
        assert_ne!(url("style.css"), url("app.js"));
        assert_eq!(url("other.txt"), "/static/other.txt");
    }
}

//! The browser player, embedded at build time from `web/` (its `dist/` is built by
//! `npm run build` and committed, so neither Node nor npm is needed to build or run cpsl).

use axum::body::Body;
use axum::extract::Path;
use axum::http::{header, HeaderMap, Response, StatusCode};

/// The page.
pub(crate) const INDEX: &str = include_str!("../../../../web/index.html");

/// The player's modules, by file name (`web/dist/`).
pub(crate) const SCRIPTS: &[(&str, &str)] = &[
    ("main.js", include_str!("../../../../web/dist/main.js")),
    ("decode.js", include_str!("../../../../web/dist/decode.js")),
    ("mp4.js", include_str!("../../../../web/dist/mp4.js")),
    (
        "package.js",
        include_str!("../../../../web/dist/package.js"),
    ),
    ("pose.js", include_str!("../../../../web/dist/pose.js")),
    ("render.js", include_str!("../../../../web/dist/render.js")),
];

fn text(body: &'static str, ctype: &'static str, headers: &HeaderMap) -> Response<Body> {
    // The build is the version: revalidate with a tag derived from the content.
    let etag = format!("\"{:016x}\"", fnv1a(body.as_bytes()));
    let builder = Response::builder()
        .header(header::CACHE_CONTROL, "no-cache")
        .header(header::ETAG, &etag)
        .header(header::X_CONTENT_TYPE_OPTIONS, "nosniff");
    let matches = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == etag));
    if matches {
        return builder
            .status(StatusCode::NOT_MODIFIED)
            .body(Body::empty())
            .expect("valid response");
    }
    builder
        .header(header::CONTENT_TYPE, ctype)
        .body(Body::from(body))
        .expect("valid response")
}

fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

pub(crate) async fn index(headers: HeaderMap) -> Response<Body> {
    text(INDEX, "text/html; charset=utf-8", &headers)
}

pub(crate) async fn asset(Path(file): Path<String>, headers: HeaderMap) -> Response<Body> {
    match SCRIPTS.iter().find(|(name, _)| *name == file) {
        Some((_, body)) => text(body, "text/javascript; charset=utf-8", &headers),
        None => crate::files::status(StatusCode::NOT_FOUND),
    }
}

#[cfg(test)]
mod tests {
    /// Every built module is embedded, and the embedded copies are the files on disk.
    #[test]
    fn every_built_module_is_embedded() {
        let dist = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../web/dist");
        let mut on_disk: Vec<String> = std::fs::read_dir(&dist)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .filter(|n| n.ends_with(".js"))
            .collect();
        on_disk.sort();
        let mut embedded: Vec<String> = super::SCRIPTS.iter().map(|s| s.0.to_string()).collect();
        embedded.sort();
        assert_eq!(on_disk, embedded, "web/dist and the embedded list differ");
        for (name, body) in super::SCRIPTS {
            assert_eq!(std::fs::read_to_string(dist.join(name)).unwrap(), *body);
        }
    }
}

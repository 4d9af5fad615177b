//! Static files under the served root: safe path resolution, content types, validators
//! (`ETag`, `Last-Modified`), conditional requests and single byte ranges.

use axum::body::Body;
use axum::http::{header, HeaderMap, HeaderValue, Method, Response, StatusCode};
use std::io::SeekFrom;
use std::path::{Path, PathBuf};
use std::time::UNIX_EPOCH;
use tokio::io::{AsyncReadExt, AsyncSeekExt};

/// Why a request path was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Refusal {
    /// Malformed or unsafe (`..`, `.`, empty components, hidden files, bad escapes, NUL,
    /// backslashes): 400.
    BadPath,
    /// Resolves (through a symbolic link) outside the root: 403.
    Escape,
    /// Does not exist or is not a regular file: 404.
    Missing,
}

impl Refusal {
    pub(crate) fn status(self) -> StatusCode {
        match self {
            Refusal::BadPath => StatusCode::BAD_REQUEST,
            Refusal::Escape => StatusCode::FORBIDDEN,
            Refusal::Missing => StatusCode::NOT_FOUND,
        }
    }
}

/// Bytes read from a file at a time.
const CHUNK: usize = 256 * 1024;
/// Longest request path accepted, in bytes (before decoding).
pub(crate) const MAX_PATH: usize = 2048;
/// Files up to this size are kept in memory once read (segment files are immutable).
const CACHE_FILE_MAX: u64 = 16 << 20;
/// Total bytes the file cache may hold.
const CACHE_TOTAL: u64 = 512 << 20;

/// Recently served small files, keyed by path and checked against the file's size and
/// modification time on every request, so a changed file is read again.
#[derive(Debug, Default)]
pub(crate) struct FileCache {
    inner: std::sync::Mutex<CacheInner>,
}

#[derive(Debug, Default)]
struct CacheInner {
    files: std::collections::HashMap<PathBuf, Cached>,
    bytes: u64,
    clock: u64,
}

#[derive(Debug)]
struct Cached {
    len: u64,
    modified: Option<std::time::SystemTime>,
    data: bytes::Bytes,
    used: u64,
}

impl FileCache {
    /// The content of `path` from memory, when it is there and still has size `len` and
    /// modification time `modified`.
    fn get(
        &self,
        path: &Path,
        len: u64,
        modified: Option<std::time::SystemTime>,
    ) -> Option<bytes::Bytes> {
        let mut c = self.inner.lock().unwrap_or_else(|e| e.into_inner());
        c.clock += 1;
        let now = c.clock;
        let f = c.files.get_mut(path)?;
        if f.len != len || f.modified != modified {
            return None;
        }
        f.used = now;
        Some(f.data.clone())
    }

    /// Reads `path` and keeps it, evicting the least recently used files beyond the budget.
    fn load(
        &self,
        path: &Path,
        len: u64,
        modified: Option<std::time::SystemTime>,
    ) -> std::io::Result<bytes::Bytes> {
        let data = bytes::Bytes::from(std::fs::read(path)?);
        if data.len() as u64 != len {
            return Err(std::io::Error::other("file changed while read"));
        }
        let mut c = self.inner.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(old) = c.files.remove(path) {
            c.bytes -= old.len;
        }
        // Evict the least recently used files until the new one fits.
        while c.bytes + len > CACHE_TOTAL && !c.files.is_empty() {
            let oldest = c
                .files
                .iter()
                .min_by_key(|(_, f)| f.used)
                .map(|(p, _)| p.clone())
                .expect("not empty");
            let f = c.files.remove(&oldest).expect("present");
            c.bytes -= f.len;
        }
        c.clock += 1;
        let used = c.clock;
        c.bytes += len;
        c.files.insert(
            path.to_path_buf(),
            Cached {
                len,
                modified,
                data: data.clone(),
                used,
            },
        );
        Ok(data)
    }
}

/// Resolves the still percent-encoded `rel` (the URL path after the route prefix) under the
/// canonical `root`: every component is decoded on its own, so an encoded `/` or `..`
/// (`%2F`, `%2e%2e`) cannot change the structure, and the result is canonicalised and must
/// still lie under `root`, so symbolic links cannot lead out of it.
pub(crate) fn resolve(root: &Path, rel: &str) -> Result<PathBuf, Refusal> {
    if rel.is_empty() || rel.len() > MAX_PATH {
        return Err(Refusal::BadPath);
    }
    let mut path = root.to_path_buf();
    for raw in rel.split('/') {
        let part = percent_encoding::percent_decode_str(raw)
            .decode_utf8()
            .map_err(|_| Refusal::BadPath)?;
        if part.is_empty()
            || part.starts_with('.')
            || part.contains(['/', '\\', '\0'])
            || part.chars().any(char::is_control)
        {
            return Err(Refusal::BadPath);
        }
        path.push(&*part);
    }
    let real = std::fs::canonicalize(&path).map_err(|_| Refusal::Missing)?;
    if !real.starts_with(root) {
        return Err(Refusal::Escape);
    }
    if !real.is_file() {
        return Err(Refusal::Missing);
    }
    Ok(real)
}

/// The content type of a file, from its extension.
pub(crate) fn content_type(path: &Path) -> &'static str {
    match path.extension().and_then(|e| e.to_str()).unwrap_or("") {
        "json" => "application/json",
        "mp4" | "m4s" => "video/mp4",
        "webm" => "video/webm",
        "html" => "text/html; charset=utf-8",
        "js" | "mjs" => "text/javascript; charset=utf-8",
        "css" => "text/css; charset=utf-8",
        "png" => "image/png",
        "jpg" | "jpeg" => "image/jpeg",
        "txt" | "md" => "text/plain; charset=utf-8",
        _ => "application/octet-stream",
    }
}

/// Whether responses of this content type are compressed (and so carry a weak validator).
pub(crate) fn compressible(content_type: &str) -> bool {
    content_type.starts_with("application/json") || content_type.starts_with("text/")
}

/// How long a client or CDN may keep a file: segment files (under `seg_NNNNNN/`) never change
/// once written, manifests and everything else are revalidated.
fn cache_control(rel: &str) -> &'static str {
    let in_segment = rel.split('/').rev().nth(1).is_some_and(|dir| {
        dir.len() > 4 && dir.starts_with("seg_") && dir[4..].bytes().all(|b| b.is_ascii_digit())
    });
    if in_segment {
        "public, max-age=31536000, immutable"
    } else {
        "no-cache"
    }
}

/// A byte range request, after parsing against the file length.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum RangeRequest {
    /// No (usable) range: the whole file.
    Full,
    /// Bytes `start..=end`.
    Part(u64, u64),
    /// Malformed or unsatisfiable: 416.
    Invalid,
}

/// Parses a `Range` header value against a file of `len` bytes. One range is served; a list
/// of several is answered with the whole file (RFC 9110 lets a server ignore ranges), and
/// anything that is not a well-formed `bytes=` range, or starts past the end, is invalid.
pub(crate) fn parse_range(value: &str, len: u64) -> RangeRequest {
    let Some(spec) = value.trim().strip_prefix("bytes=") else {
        return RangeRequest::Invalid;
    };
    let specs: Vec<&str> = spec.split(',').map(str::trim).collect();
    let parsed: Option<Vec<(Option<u64>, Option<u64>)>> = specs
        .iter()
        .map(|s| {
            let (a, b) = s.split_once('-')?;
            let num = |t: &str| -> Option<Option<u64>> {
                if t.is_empty() {
                    Some(None)
                } else if t.bytes().all(|c| c.is_ascii_digit()) && t.len() <= 19 {
                    t.parse().ok().map(Some)
                } else {
                    None
                }
            };
            let (a, b) = (num(a)?, num(b)?);
            match (a, b) {
                (None, None) => None,
                (Some(a), Some(b)) if b < a => None,
                _ => Some((a, b)),
            }
        })
        .collect();
    let Some(parsed) = parsed else {
        return RangeRequest::Invalid;
    };
    if parsed.len() != 1 {
        return RangeRequest::Full;
    }
    match parsed[0] {
        (Some(a), _) if a >= len => RangeRequest::Invalid,
        (Some(a), None) => RangeRequest::Part(a, len - 1),
        (Some(a), Some(b)) => RangeRequest::Part(a, b.min(len - 1)),
        (None, Some(0)) => RangeRequest::Invalid,
        (None, Some(_)) if len == 0 => RangeRequest::Invalid,
        (None, Some(n)) => RangeRequest::Part(len - n.min(len), len - 1),
        (None, None) => RangeRequest::Invalid,
    }
}

/// Whether an `If-None-Match` / `If-Range` list names `etag` (weak comparison).
fn etag_matches(list: &str, etag: &str) -> bool {
    let bare = |t: &str| t.trim().trim_start_matches("W/").to_string();
    list.trim() == "*" || list.split(',').any(|t| bare(t) == bare(etag))
}

/// What the blocking part of a request found: the file's metadata and, for small files, its
/// content.
struct Found {
    path: PathBuf,
    len: u64,
    modified: Option<std::time::SystemTime>,
    data: Option<bytes::Bytes>,
}

/// Answers a GET or HEAD for `rel` (the still percent-encoded path under the route) below the
/// canonical `root`. Path resolution and metadata are a few quick system calls and run in
/// place; reading a small file that is not in memory yet runs as a blocking task, and small
/// files are then served from memory.
pub(crate) async fn serve(
    root: &Path,
    cache: &std::sync::Arc<FileCache>,
    rel: &str,
    method: &Method,
    headers: &HeaderMap,
) -> Response<Body> {
    let found = resolve(root, rel).and_then(|path| {
        let meta = std::fs::metadata(&path).map_err(|_| Refusal::Missing)?;
        Ok((path, meta.len(), meta.modified().ok()))
    });
    let (path, len, modified) = match found {
        Ok(f) => f,
        Err(refusal) => {
            tracing::warn!(path = rel, ?refusal, "refused");
            return status(refusal.status());
        }
    };
    let data = if *method != Method::HEAD && len <= CACHE_FILE_MAX {
        let hit = cache.get(&path, len, modified);
        match hit {
            Some(d) => Some(d),
            None => {
                let (cache, p) = (cache.clone(), path.clone());
                match tokio::task::spawn_blocking(move || cache.load(&p, len, modified)).await {
                    Ok(Ok(d)) => Some(d),
                    _ => return status(StatusCode::NOT_FOUND),
                }
            }
        }
    } else {
        None
    };
    let found = Found {
        path,
        len,
        modified,
        data,
    };
    respond(found, rel, method, headers).await
}

async fn respond(found: Found, rel: &str, method: &Method, headers: &HeaderMap) -> Response<Body> {
    let Found {
        path,
        len,
        modified,
        data,
    } = found;
    let nanos = modified
        .and_then(|m| m.duration_since(UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_nanos());
    let ctype = content_type(&path);
    // Compressed responses differ byte for byte from the file: their validator is weak.
    let etag = if compressible(ctype) {
        format!("W/\"{len:x}-{nanos:x}\"")
    } else {
        format!("\"{len:x}-{nanos:x}\"")
    };
    let mut builder = Response::builder()
        .header(header::ETAG, &etag)
        .header(header::CACHE_CONTROL, cache_control(rel))
        .header(header::ACCEPT_RANGES, "bytes")
        .header(header::X_CONTENT_TYPE_OPTIONS, "nosniff");
    if let Some(m) = modified {
        builder = builder.header(header::LAST_MODIFIED, httpdate::fmt_http_date(m));
    }
    let text = |name| {
        headers
            .get(name)
            .and_then(|v: &HeaderValue| v.to_str().ok())
    };
    if text(header::IF_NONE_MATCH).is_some_and(|l| etag_matches(l, &etag)) {
        return builder
            .status(StatusCode::NOT_MODIFIED)
            .body(Body::empty())
            .expect("valid response");
    }
    let mut range = match text(header::RANGE) {
        Some(r) => parse_range(r, len),
        None if headers.contains_key(header::RANGE) => RangeRequest::Invalid,
        None => RangeRequest::Full,
    };
    // A range applies only while the representation is the one the client holds.
    if let Some(v) = text(header::IF_RANGE) {
        if !(v.starts_with('"') && v == etag) {
            range = RangeRequest::Full;
        }
    }
    let (code, start, count) = match range {
        RangeRequest::Full => (StatusCode::OK, 0, len),
        RangeRequest::Part(a, b) => {
            builder = builder.header(header::CONTENT_RANGE, format!("bytes {a}-{b}/{len}"));
            (StatusCode::PARTIAL_CONTENT, a, b - a + 1)
        }
        RangeRequest::Invalid => {
            return builder
                .status(StatusCode::RANGE_NOT_SATISFIABLE)
                .header(header::CONTENT_RANGE, format!("bytes */{len}"))
                .body(Body::empty())
                .expect("valid response");
        }
    };
    let builder = builder
        .status(code)
        .header(header::CONTENT_TYPE, ctype)
        .header(header::CONTENT_LENGTH, count);
    if method == Method::HEAD {
        return builder.body(Body::empty()).expect("valid response");
    }
    if let Some(data) = data {
        let body = data.slice(start as usize..(start + count) as usize);
        return builder.body(Body::from(body)).expect("valid response");
    }
    let mut file = match tokio::fs::File::open(&path).await {
        Ok(f) => f,
        Err(_) => return status(StatusCode::NOT_FOUND),
    };
    if start > 0 && file.seek(SeekFrom::Start(start)).await.is_err() {
        return status(StatusCode::INTERNAL_SERVER_ERROR);
    }
    // A body of one read goes out with the headers (a layer fragment is a few kB): streamed,
    // it would follow them after a trip through the blocking pool, which a client measuring
    // its link (the browser player) would count as transfer time.
    if count <= CHUNK as u64 {
        let mut body = vec![0u8; count as usize];
        return match file.read_exact(&mut body).await {
            Ok(_) => builder.body(Body::from(body)).expect("valid response"),
            Err(_) => status(StatusCode::INTERNAL_SERVER_ERROR),
        };
    }
    let stream = tokio_util::io::ReaderStream::with_capacity(file.take(count), CHUNK);
    builder
        .body(Body::from_stream(stream))
        .expect("valid response")
}

/// An empty response with `code`.
pub(crate) fn status(code: StatusCode) -> Response<Body> {
    Response::builder()
        .status(code)
        .header(header::CONTENT_TYPE, "text/plain; charset=utf-8")
        .body(Body::from(format!("{code}\n")))
        .expect("valid response")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges() {
        use RangeRequest::*;
        let len = 100;
        assert_eq!(parse_range("bytes=0-9", len), Part(0, 9));
        assert_eq!(parse_range("bytes=90-", len), Part(90, 99));
        assert_eq!(parse_range("bytes=-10", len), Part(90, 99));
        assert_eq!(parse_range("bytes=-1000", len), Part(0, 99));
        assert_eq!(parse_range("bytes=50-1000", len), Part(50, 99));
        assert_eq!(parse_range("bytes=0-1,5-6", len), Full);
        for bad in [
            "bytes=100-",
            "bytes=9-0",
            "bytes=-0",
            "bytes=abc",
            "bytes=-",
            "items=0-1",
            "bytes=0-1,x",
            "bytes=+1-2",
            "bytes=99999999999999999999-",
        ] {
            assert_eq!(parse_range(bad, len), Invalid, "{bad}");
        }
        assert_eq!(parse_range("bytes=-5", 0), Invalid);
    }

    #[test]
    fn cache_policy() {
        assert_eq!(
            cache_control("a.cpsl/seg_000001/layer_00.mp4"),
            "public, max-age=31536000, immutable"
        );
        assert_eq!(cache_control("a.cpsl/manifest.json"), "no-cache");
        assert_eq!(cache_control("seg_x/layer.mp4"), "no-cache");
    }

    #[test]
    fn etag_lists() {
        assert!(etag_matches("\"a\", W/\"b\"", "\"b\""));
        assert!(etag_matches("*", "\"b\""));
        assert!(!etag_matches("\"a\"", "\"b\""));
    }

    #[test]
    fn paths() {
        let dir = tempfile::tempdir().unwrap();
        let root = std::fs::canonicalize(dir.path()).unwrap();
        std::fs::create_dir(root.join("p")).unwrap();
        std::fs::write(root.join("p/f.json"), b"{}").unwrap();
        assert!(resolve(&root, "p/f.json").is_ok());
        assert!(resolve(&root, "p%2Ff.json").is_err());
        for bad in [
            "../x",
            "p/../p/f.json",
            "%2e%2e/x",
            ".hidden",
            "p//f.json",
            "",
            "p\\f",
        ] {
            assert_eq!(resolve(&root, bad), Err(Refusal::BadPath), "{bad}");
        }
        assert_eq!(resolve(&root, "p"), Err(Refusal::Missing));
        assert_eq!(resolve(&root, "nope"), Err(Refusal::Missing));
    }
}

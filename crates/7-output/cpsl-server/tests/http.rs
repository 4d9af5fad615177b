//! The server over loopback, spoken to with raw HTTP/1.1 (so that no client normalises a
//! hostile path first): ranges, validators, traversal attempts, limits, concurrency and
//! graceful shutdown.

use cpsl_server::{router, serve, ServerConfig};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

const SECRET: &str = "top-secret-outside-the-root";

struct Server {
    addr: SocketAddr,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
    _dir: tempfile::TempDir,
    segment: Vec<u8>,
}

impl Server {
    fn start() -> Self {
        Self::start_with(ServerConfig::default())
    }

    fn start_with(cfg: ServerConfig) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let base = dir.path();
        let root = base.join("root");
        let pkg = root.join("clip.cpsl");
        std::fs::create_dir_all(pkg.join("seg_000000")).unwrap();
        let manifest = format!(
            "{{\"format\": \"cpsl-package\", \"pad\": \"{}\"}}",
            "x".repeat(2000)
        );
        std::fs::write(pkg.join("manifest.json"), manifest).unwrap();
        let segment: Vec<u8> = (0..100_000u32).map(|i| (i * 7 % 251) as u8).collect();
        std::fs::write(pkg.join("seg_000000/layer_00.mp4"), &segment).unwrap();
        std::fs::write(pkg.join(".hidden"), SECRET).unwrap();
        std::fs::create_dir(base.join("outside")).unwrap();
        std::fs::write(base.join("outside/secret.txt"), SECRET).unwrap();
        std::fs::write(base.join("secret.txt"), SECRET).unwrap();
        std::os::unix::fs::symlink(base.join("secret.txt"), root.join("escape.txt")).unwrap();
        std::os::unix::fs::symlink(base.join("outside"), root.join("dirlink")).unwrap();
        std::os::unix::fs::symlink(pkg.join("manifest.json"), root.join("inside.json")).unwrap();
        let app = router(&root, &cfg).unwrap();
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let (addr_tx, addr_rx) = std::sync::mpsc::channel();
        let thread = std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()
                .unwrap();
            rt.block_on(async move {
                let l = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
                addr_tx.send(l.local_addr().unwrap()).unwrap();
                let stop = async {
                    let _ = rx.await;
                };
                serve(l, app, &cfg, stop, Duration::from_secs(5))
                    .await
                    .unwrap();
            });
        });
        Server {
            addr: addr_rx.recv().unwrap(),
            stop: Some(tx),
            thread: Some(thread),
            _dir: dir,
            segment,
        }
    }

    fn stop(&mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        if let Some(t) = self.thread.take() {
            t.join().unwrap();
        }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.stop();
    }
}

#[derive(Debug)]
struct Reply {
    status: u16,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Reply {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }
}

/// Sends one raw request (`Connection: close`) and reads the whole reply.
fn raw(addr: SocketAddr, head: &str) -> Reply {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    s.write_all(head.as_bytes()).unwrap();
    let mut buf = Vec::new();
    s.read_to_end(&mut buf).unwrap();
    parse(&buf)
}

fn parse(buf: &[u8]) -> Reply {
    let end = buf
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("header end");
    let text = String::from_utf8_lossy(&buf[..end]).to_string();
    let mut lines = text.split("\r\n");
    let status = lines
        .next()
        .unwrap()
        .split(' ')
        .nth(1)
        .unwrap()
        .parse()
        .unwrap();
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(": "))
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
    let mut body = buf[end + 4..].to_vec();
    let chunked = headers
        .iter()
        .any(|(k, v)| k.eq_ignore_ascii_case("transfer-encoding") && v == "chunked");
    if chunked {
        let mut out = Vec::new();
        let mut rest = &body[..];
        loop {
            let nl = rest.windows(2).position(|w| w == b"\r\n").unwrap();
            let n = usize::from_str_radix(std::str::from_utf8(&rest[..nl]).unwrap().trim(), 16)
                .unwrap();
            if n == 0 {
                break;
            }
            out.extend_from_slice(&rest[nl + 2..nl + 2 + n]);
            rest = &rest[nl + 4 + n..];
        }
        body = out;
    }
    Reply {
        status,
        headers,
        body,
    }
}

fn get(addr: SocketAddr, path: &str, extra: &[(&str, &str)]) -> Reply {
    let mut head = format!("GET {path} HTTP/1.1\r\nHost: test\r\nConnection: close\r\n");
    for (k, v) in extra {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    head.push_str("\r\n");
    raw(addr, &head)
}

const SEG: &str = "/files/clip.cpsl/seg_000000/layer_00.mp4";

#[test]
fn whole_files_and_headers() {
    let s = Server::start();
    let r = get(s.addr, SEG, &[("Origin", "http://elsewhere.example")]);
    assert_eq!(r.status, 200);
    assert_eq!(r.body, s.segment);
    assert_eq!(r.header("content-type"), Some("video/mp4"));
    assert_eq!(r.header("content-length"), Some("100000"));
    assert_eq!(r.header("accept-ranges"), Some("bytes"));
    assert_eq!(
        r.header("cache-control"),
        Some("public, max-age=31536000, immutable")
    );
    assert_eq!(r.header("access-control-allow-origin"), Some("*"));
    assert!(r.header("etag").unwrap().starts_with('"'));
    assert!(r.header("last-modified").is_some());

    let m = get(s.addr, "/files/clip.cpsl/manifest.json", &[]);
    assert_eq!(m.status, 200);
    assert_eq!(m.header("cache-control"), Some("no-cache"));
    assert_eq!(m.header("content-type"), Some("application/json"));
    // A symbolic link that stays inside the root is served.
    assert_eq!(get(s.addr, "/files/inside.json", &[]).body, m.body);

    let head = raw(
        s.addr,
        &format!("HEAD {SEG} HTTP/1.1\r\nHost: t\r\nConnection: close\r\n\r\n"),
    );
    assert_eq!(head.status, 200);
    assert_eq!(head.header("content-length"), Some("100000"));
    assert!(head.body.is_empty());
}

#[test]
fn byte_ranges() {
    let s = Server::start();
    let seg = &s.segment;
    for (range, a, b) in [
        ("bytes=10-19", 10, 19),
        ("bytes=99990-", 99990, 99999),
        ("bytes=-5", 99995, 99999),
        ("bytes=0-0", 0, 0),
        ("bytes=50000-200000", 50000, 99999),
    ] {
        let r = get(s.addr, SEG, &[("Range", range)]);
        assert_eq!(r.status, 206, "{range}");
        assert_eq!(r.body, &seg[a..=b], "{range}");
        assert_eq!(
            r.header("content-range").unwrap(),
            format!("bytes {a}-{b}/100000")
        );
        assert_eq!(r.header("content-length").unwrap(), (b - a + 1).to_string());
    }
    for bad in [
        "bytes=100000-",
        "bytes=20-10",
        "bytes=abc",
        "bytes=-0",
        "lines=1-2",
        "bytes=--1",
        "bytes=1-2-3",
    ] {
        let r = get(s.addr, SEG, &[("Range", bad)]);
        assert_eq!(r.status, 416, "{bad}");
        assert_eq!(r.header("content-range"), Some("bytes */100000"), "{bad}");
        assert!(r.body.is_empty());
    }
    // Several ranges: the whole file.
    let r = get(s.addr, SEG, &[("Range", "bytes=0-1,5-6")]);
    assert_eq!((r.status, r.body.len()), (200, 100_000));
    // Ranges are not compressed even when the client accepts it.
    let r = get(
        s.addr,
        "/files/clip.cpsl/manifest.json",
        &[("Range", "bytes=0-9"), ("Accept-Encoding", "gzip, br")],
    );
    assert_eq!(r.status, 206);
    assert_eq!(r.header("content-encoding"), None);
    assert_eq!(r.body, b"{\"format\":");
}

#[test]
fn validators() {
    let s = Server::start();
    let first = get(s.addr, SEG, &[]);
    let etag = first.header("etag").unwrap().to_string();
    let r = get(s.addr, SEG, &[("If-None-Match", &etag)]);
    assert_eq!(r.status, 304);
    assert!(r.body.is_empty());
    assert_eq!(r.header("etag"), Some(etag.as_str()));
    let r = get(s.addr, SEG, &[("If-None-Match", "\"other\"")]);
    assert_eq!(r.status, 200);
    // If-Range: the range only while the representation is unchanged.
    let r = get(s.addr, SEG, &[("Range", "bytes=0-9"), ("If-Range", &etag)]);
    assert_eq!((r.status, r.body.len()), (206, 10));
    let r = get(
        s.addr,
        SEG,
        &[("Range", "bytes=0-9"), ("If-Range", "\"stale\"")],
    );
    assert_eq!((r.status, r.body.len()), (200, 100_000));
    // Manifests are compressed, and then carry a weak validator.
    let m = get(
        s.addr,
        "/files/clip.cpsl/manifest.json",
        &[("Accept-Encoding", "br")],
    );
    assert_eq!(m.header("content-encoding"), Some("br"));
    assert!(m.body.len() < 500, "{} bytes", m.body.len());
    let weak = m.header("etag").unwrap().to_string();
    assert!(weak.starts_with("W/"));
    let m = get(
        s.addr,
        "/files/clip.cpsl/manifest.json",
        &[("Accept-Encoding", "gzip")],
    );
    assert_eq!(m.header("content-encoding"), Some("gzip"));
    let r = get(
        s.addr,
        "/files/clip.cpsl/manifest.json",
        &[("If-None-Match", &weak), ("Accept-Encoding", "gzip")],
    );
    assert_eq!(r.status, 304);
}

#[test]
fn traversal_is_refused() {
    let s = Server::start();
    for path in [
        "/files/../secret.txt",
        "/files/../../etc/passwd",
        "/files/%2e%2e/secret.txt",
        "/files/%2E%2E/secret.txt",
        "/files/clip.cpsl/%2e%2e/%2e%2e/secret.txt",
        "/files/..%2fsecret.txt",
        "/files/%2e%2e%2fsecret.txt",
        "/files/%2fetc%2fpasswd",
        "/files//etc/passwd",
        "/files/..%5csecret.txt",
        "/files/.%2e/secret.txt",
        "/files/clip.cpsl/.hidden",
        "/files/escape.txt",
        "/files/dirlink/secret.txt",
        "/files/%252e%252e/secret.txt",
        "/files/clip.cpsl/manifest.json%00.mp4",
        "/files/%ff%fe",
        "/../secret.txt",
        "/player/../../secret.txt",
        "/files/clip.cpsl",
        "/files/",
    ] {
        let r = get(s.addr, path, &[]);
        assert!(
            matches!(r.status, 400 | 403 | 404),
            "{path}: status {}",
            r.status
        );
        assert!(
            !String::from_utf8_lossy(&r.body).contains(SECRET),
            "{path} leaked the secret"
        );
    }
    // An absolute-form request target names no file of ours either.
    let r = raw(
        s.addr,
        "GET http://test/etc/passwd HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n",
    );
    assert_eq!(r.status, 404);
    // The symbolic link out of the root: 403, not 404, so the refusal is visible in logs.
    assert_eq!(get(s.addr, "/files/escape.txt", &[]).status, 403);
}

#[test]
fn methods_bodies_and_long_uris_are_refused() {
    let s = Server::start();
    let r = raw(
        s.addr,
        &format!(
            "POST {SEG} HTTP/1.1\r\nHost: t\r\nConnection: close\r\nContent-Length: 0\r\n\r\n"
        ),
    );
    assert_eq!(r.status, 405);
    let r = raw(
        s.addr,
        &format!(
            "GET {SEG} HTTP/1.1\r\nHost: t\r\nConnection: close\r\nContent-Length: 5\r\n\r\nhello"
        ),
    );
    assert_eq!(r.status, 413);
    let long = format!("/files/{}", "a/".repeat(2000));
    assert_eq!(get(s.addr, &long, &[]).status, 414);
    // The player and its scripts.
    let r = get(s.addr, "/", &[]);
    assert_eq!(r.status, 200);
    assert!(String::from_utf8_lossy(&r.body).contains("player/main.js"));
    let r = get(s.addr, "/player/main.js", &[]);
    assert_eq!(
        r.header("content-type"),
        Some("text/javascript; charset=utf-8")
    );
    let etag = r.header("etag").unwrap().to_string();
    assert_eq!(
        get(s.addr, "/player/main.js", &[("If-None-Match", &etag)]).status,
        304
    );
    assert_eq!(get(s.addr, "/player/nope.js", &[]).status, 404);
}

#[test]
fn slow_clients_time_out() {
    let s = Server::start_with(ServerConfig {
        header_timeout: Duration::from_millis(500),
        ..ServerConfig::default()
    });
    let mut c = TcpStream::connect(s.addr).unwrap();
    c.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    c.write_all(b"GET / HTTP/1.1\r\nHost: t\r\n").unwrap();
    let t = Instant::now();
    let mut buf = Vec::new();
    let _ = c.read_to_end(&mut buf);
    assert!(t.elapsed() < Duration::from_secs(5), "{:?}", t.elapsed());
    // The server still answers others.
    assert_eq!(get(s.addr, SEG, &[("Range", "bytes=0-0")]).status, 206);
}

#[test]
fn concurrent_clients() {
    let s = Server::start();
    let addr = s.addr;
    let seg = std::sync::Arc::new(s.segment.clone());
    let threads: Vec<_> = (0..32)
        .map(|t| {
            let seg = seg.clone();
            std::thread::spawn(move || {
                // Keep-alive: many requests on one connection.
                let mut c = TcpStream::connect(addr).unwrap();
                c.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
                for i in 0..20usize {
                    let a = (t * 997 + i * 131) % 90_000;
                    let b = a + 1 + (i * 37) % 5000;
                    let head =
                        format!("GET {SEG} HTTP/1.1\r\nHost: t\r\nRange: bytes={a}-{b}\r\n\r\n");
                    c.write_all(head.as_bytes()).unwrap();
                    let body = read_one(&mut c);
                    assert_eq!(body, &seg[a..=b]);
                }
            })
        })
        .collect();
    for t in threads {
        t.join().unwrap();
    }
}

/// Reads one response with a Content-Length from a kept-alive connection.
fn read_one(c: &mut TcpStream) -> Vec<u8> {
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        c.read_exact(&mut byte).unwrap();
        head.push(byte[0]);
    }
    let text = String::from_utf8(head).unwrap();
    assert!(text.starts_with("HTTP/1.1 206"), "{text}");
    let len: usize = text
        .lines()
        .find_map(|l| {
            l.to_ascii_lowercase()
                .strip_prefix("content-length: ")
                .map(|v| v.trim().parse().unwrap())
        })
        .unwrap();
    let mut body = vec![0u8; len];
    c.read_exact(&mut body).unwrap();
    body
}

#[test]
fn graceful_shutdown_stops_listening() {
    let mut s = Server::start();
    let addr = s.addr;
    assert_eq!(get(addr, SEG, &[("Range", "bytes=0-0")]).status, 206);
    let t = Instant::now();
    s.stop();
    assert!(t.elapsed() < Duration::from_secs(5));
    assert!(TcpStream::connect(addr).is_err(), "still listening");
}

#[test]
fn bounded_load_has_no_errors() {
    let s = Server::start();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let report = rt.block_on(cpsl_server::run_load(&cpsl_server::LoadConfig {
        addr: s.addr,
        paths: vec![SEG.into(), "/files/clip.cpsl/manifest.json".into()],
        clients: 50,
        duration: Duration::from_millis(500),
    }));
    assert_eq!(report.errors, 0);
    assert!(report.requests >= 50, "{report:?}");
    assert!(report.p50_ms <= report.p99_ms && report.p99_ms <= report.max_ms);
}
